"""The backend's per-CPU choices (`scenegen_jax.backend`) on each kind of CPU the project runs
on, from faked CPU answers (the choices `backend`'s docstrings state), and its AVX-512 test
against the kernel's own flags. `tests/test_avx2_only.py` runs the same choices under a
real CPUID that hides AVX-512, where the host allows it."""

import os

import pytest

from scenegen_jax import backend


@pytest.mark.parametrize("vendor,avx512,eigen,bands,winograd", [
    ("GenuineIntel", True, True, (32, 32), False),  # Xeon with AVX-512 and AMX
    ("AuthenticAMD", True, False, (128, 64), False),  # EPYC Zen 4 / Zen 5
    ("AuthenticAMD", False, True, (32, 32), True),  # EPYC Zen 3: AVX2 only
    ("GenuineIntel", False, True, (32, 32), True),  # AVX-512 hidden (bench/avx2_only.c)
])
def test_choices_by_cpu(monkeypatch, vendor, avx512, eigen, bands, winograd):
    monkeypatch.setattr(backend, "on_cpu", lambda: True)
    monkeypatch.setattr(backend, "cpu_vendor", lambda: vendor)
    monkeypatch.setattr(backend, "cpu_has_avx512", lambda: avx512)
    assert backend.train_eigen_convolutions() == eigen
    assert backend.weight_gradient_bands() == bands
    assert backend.winograd_convolutions((5, 5), backend.WINOGRAD_MAX_TILES) == winograd
    assert not backend.winograd_convolutions((5, 5), backend.WINOGRAD_MAX_TILES + 1)
    assert not backend.winograd_convolutions((3, 3), 1)


def test_accelerators_keep_their_own(monkeypatch):
    monkeypatch.setattr(backend, "on_cpu", lambda: False)
    monkeypatch.setattr(backend, "cpu_has_avx512", lambda: False)
    assert not backend.train_eigen_convolutions()
    assert backend.weight_gradient_bands() is None
    assert not backend.winograd_convolutions((5, 5), 1)


@pytest.mark.skipif(not os.path.exists("/proc/cpuinfo"), reason="needs Linux's /proc/cpuinfo")
def test_avx512_as_the_kernel_lists_it():
    with open("/proc/cpuinfo") as f:
        flags = next(line.split(":", 1)[1].split() for line in f if line.startswith("flags"))
    assert backend.cpu_has_avx512() == ("avx512f" in flags)
