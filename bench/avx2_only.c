/* An AVX2-only CPU on a wider x86 one, for `bench/run.py --isa AVX2`.

   Loaded with LD_PRELOAD, it makes the CPUID instruction fault in this process and every
   thread and child it starts (Linux's ARCH_SET_CPUID, where the CPU supports CPUID faulting:
   the `cpuid_fault` flag of /proc/cpuinfo), and answers each CPUID itself: the real answer
   with the AVX-512, AMX, AVX-VNNI and AVX10 bits cleared. Every library that picks its
   kernels from CPUID at run time then picks its AVX2 ones: YNNPACK (through cpuinfo), oneDNN,
   XLA's LLVM host features, PyTorch's ATen dispatch. XLA_FLAGS' --xla_cpu_max_isa caps only
   the code XLA generates, and ONEDNN_MAX_CPU_ISA only oneDNN, and neither reaches YNNPACK
   (docs/performance.md).

   What it cannot reach: code that chose its ISA before this library's constructor ran (the
   dynamic loader's and glibc's string functions), and XCR0 (xgetbv still reports the
   AVX-512 register state, which no library uses once CPUID clears the feature bits).

   Build: cc -O2 -shared -fPIC -o avx2_only.so avx2_only.c
   Check: LD_PRELOAD=./avx2_only.so grep -c avx512 /proc/cpuinfo  (the kernel's view: unchanged)
          LD_PRELOAD=./avx2_only.so python -c "..."                (libraries' view: AVX2) */

#define _GNU_SOURCE
#include <asm/prctl.h>
#include <signal.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/syscall.h>
#include <ucontext.h>
#include <unistd.h>

static void set_cpuid_faulting(int on) {
  /* ARCH_SET_CPUID's argument is whether CPUID is allowed. */
  syscall(SYS_arch_prctl, ARCH_SET_CPUID, on ? 0 : 1);
}

static void real_cpuid(uint32_t leaf, uint32_t subleaf, uint32_t r[4]) {
  __asm__ volatile("cpuid" : "=a"(r[0]), "=b"(r[1]), "=c"(r[2]), "=d"(r[3])
                   : "a"(leaf), "c"(subleaf));
}

static void mask_wider_than_avx2(uint32_t leaf, uint32_t subleaf, uint32_t r[4]) {
  if (leaf == 7 && subleaf == 0) {
    /* EBX: AVX512F 16, DQ 17, IFMA 21, PF 26, ER 27, CD 28, BW 30, VL 31. */
    r[1] &= ~((1u << 16) | (1u << 17) | (1u << 21) | (1u << 26) | (1u << 27) | (1u << 28) |
              (1u << 30) | (1u << 31));
    /* ECX: VBMI 1, VBMI2 6, VNNI 11, BITALG 12, VPOPCNTDQ 14. */
    r[2] &= ~((1u << 1) | (1u << 6) | (1u << 11) | (1u << 12) | (1u << 14));
    /* EDX: 4VNNIW 2, 4FMAPS 3, VP2INTERSECT 8, AMX-BF16 22, AVX512-FP16 23, AMX-TILE 24,
       AMX-INT8 25. */
    r[3] &= ~((1u << 2) | (1u << 3) | (1u << 8) | (1u << 22) | (1u << 23) | (1u << 24) |
              (1u << 25));
  } else if (leaf == 7 && subleaf == 1) {
    /* EAX: AVX-VNNI 4, AVX512-BF16 5, AMX-FP16 21; EDX: AVX10 19. */
    r[0] &= ~((1u << 4) | (1u << 5) | (1u << 21));
    r[3] &= ~(1u << 19);
  } else if (leaf == 0x1d || leaf == 0x1e || leaf == 0x24) {
    /* AMX tile and TMUL information, AVX10 information. */
    r[0] = r[1] = r[2] = r[3] = 0;
  }
}

static void on_sigsegv(int sig, siginfo_t *info, void *context) {
  ucontext_t *uc = context;
  greg_t *g = uc->uc_mcontext.gregs;
  const unsigned char *ip = (const unsigned char *)g[REG_RIP];
  if (ip[0] != 0x0f || ip[1] != 0xa2) { /* not CPUID: a real fault */
    signal(SIGSEGV, SIG_DFL);
    raise(SIGSEGV);
    return;
  }
  uint32_t leaf = (uint32_t)g[REG_RAX], subleaf = (uint32_t)g[REG_RCX], r[4];
  set_cpuid_faulting(0);
  real_cpuid(leaf, subleaf, r);
  set_cpuid_faulting(1);
  mask_wider_than_avx2(leaf, subleaf, r);
  g[REG_RAX] = r[0];
  g[REG_RBX] = r[1];
  g[REG_RCX] = r[2];
  g[REG_RDX] = r[3];
  g[REG_RIP] += 2;
  (void)sig;
  (void)info;
}

__attribute__((constructor)) static void start(void) {
  struct sigaction sa;
  memset(&sa, 0, sizeof sa);
  sa.sa_sigaction = on_sigsegv;
  sa.sa_flags = SA_SIGINFO | SA_NODEFER;
  sigemptyset(&sa.sa_mask);
  if (sigaction(SIGSEGV, &sa, NULL) != 0 ||
      syscall(SYS_arch_prctl, ARCH_SET_CPUID, 0) != 0) {
    fprintf(stderr, "avx2_only: this CPU or kernel has no CPUID faulting (cpuid_fault)\n");
    exit(3);
  }
}
