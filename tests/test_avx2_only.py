"""`bench/avx2_only.c`, the AVX2-only CPU of `make bench ISA=AVX2`: the kernel libraries'
view of CPUID loses AVX-512 and AMX and keeps AVX2, the backend then takes its AVX2-only
choices, and a real crash still crashes."""

import os
import platform
import shutil
import subprocess
import sys

import pytest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _flags() -> list[str]:
    with open("/proc/cpuinfo") as f:
        return next((line.split(":", 1)[1].split() for line in f if line.startswith("flags")), [])


pytestmark = pytest.mark.skipif(
    platform.machine() != "x86_64" or shutil.which("cc") is None
    or "cpuid_fault" not in _flags(),
    reason="needs x86-64 Linux with CPUID faulting and a C compiler")


@pytest.fixture(scope="module")
def preload(tmp_path_factory):
    lib = tmp_path_factory.mktemp("avx2_only") / "avx2_only.so"
    subprocess.run(["cc", "-O2", "-shared", "-fPIC", "-o", str(lib),
                    os.path.join(REPO, "bench", "avx2_only.c")], check=True)
    return {**os.environ, "LD_PRELOAD": str(lib)}


def _python(code: str, env: dict) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                          cwd=REPO)


def test_libraries_see_avx2_without_avx512(preload):
    code = ("from numpy._core._multiarray_umath import __cpu_features__ as f;"
            "print(f['AVX'], f['AVX2'], f['FMA3'], f['AVX512F'], f['AVX512_SPR'])")
    real = _python(code, dict(os.environ)).stdout.split()
    hidden = _python(code, preload)
    assert hidden.returncode == 0, hidden.stderr
    assert real[:3] == ["True", "True", "True"]  # the kernel's view: /proc/cpuinfo has avx2
    assert hidden.stdout.split() == ["True", "True", "True", "False", "False"]


def test_backend_takes_its_avx2_only_choices(preload):
    code = ("from scenegen_jax import backend;"
            "print(backend.cpu_has_avx512(), backend.train_eigen_convolutions(),"
            " backend.weight_gradient_bands(), backend.winograd_convolutions((5, 5), 1024),"
            " backend.winograd_convolutions((5, 5), 1025),"
            " backend.winograd_convolutions((3, 3), 1))")
    out = _python(code, preload)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["False", "True", "(32,", "32)", "True", "False", "False"]


def test_a_real_segfault_still_kills_the_process(preload):
    out = _python("import ctypes; ctypes.string_at(0)", preload)
    assert out.returncode == -11
