"""Another kind of x86-64 CPU on this machine: QEMU's user-mode emulator runs one process with the CPUID
of another CPU model, so the libraries choose the kernels they would choose there.

The committed results must be the same bytes on every x86-64 CPU with AVX2 and FMA, Intel or AMD, with
or without AVX-512 (cosim/base/numeric_env.py, controllers/lbfgs.py). One machine cannot be two CPUs;
``qemu-x86_64 -cpu MODEL`` (Debian's ``qemu-user``, which ``make`` installs when run as root) can make a
process believe it is: it emulates every instruction (QEMU 7.2's TCG has AVX2 and FMA, not AVX-512) and
answers CPUID as ``MODEL`` does, so MKL, OpenBLAS, Sleef, numpy and glibc take that CPU's code paths. Its
floating point is IEEE-exact (softfloat), so a difference it shows is the libraries', not the
emulator's -- checked: ``np.sqrt``, ``math.sqrt`` and glibc's ``exp``/``pow``/``sin`` give the host's
bits, ``torch.sqrt`` and ``torch.log`` do not. It is slow (20-50 x), so only small jobs run under it:
the test of tests/test_numeric_env.py and the benchmark group ``numeric-env``.
"""

from __future__ import annotations

import platform
import shutil

QEMU = "qemu-x86_64"
#: the emulated CPUs: Intel Haswell (AVX2, FMA, no AVX-512) and AMD Zen 2 (the same ISA, the other vendor)
HASWELL, ZEN2 = "Haswell-v4", "EPYC-Rome"
DESCRIPTIONS = {HASWELL: "Intel Haswell (AVX2 and FMA, no AVX-512)", ZEN2: "AMD Zen 2 / EPYC Rome (AVX2 and FMA, "
                                                                          "no AVX-512)"}


def not_x86_64() -> str | None:
    """Why this host is not an x86-64 one (None: it is)."""
    return None if platform.machine() in ("x86_64", "AMD64") else f"the host is {platform.machine()}, not x86-64"


def problem() -> str | None:
    """Why no other CPU can be emulated here (None: it can)."""
    if not_x86_64():
        return not_x86_64()
    if shutil.which(QEMU) is None:
        return f"{QEMU} is not installed (Debian package qemu-user; `make` installs it when run as root)"
    return None


def _host() -> tuple[str, set[str]]:
    vendor, flags = "", set()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as handle:
            for line in handle:
                key, _, value = line.partition(":")
                if key.strip() == "vendor_id" and not vendor:
                    vendor = value.strip()
                elif key.strip() == "flags" and not flags:
                    flags = set(value.split())
                if vendor and flags:
                    break
    except OSError:
        pass
    return vendor, flags


def contrasting_model() -> str:
    """A CPU model unlike the host within the range the results must hold on: without AVX-512 when the
    host has it, else of the other vendor."""
    vendor, flags = _host()
    if "avx512f" in flags:
        return HASWELL
    return ZEN2 if vendor == "GenuineIntel" else HASWELL


def command(argv: list[str], model: str | None = None) -> list[str]:
    """``argv`` (a program and its arguments) run on the emulated CPU ``model`` (default: :func:`contrasting_model`)."""
    return [QEMU, "-cpu", model or contrasting_model(), *argv]
