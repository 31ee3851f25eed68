"""The numeric kernels every workbench process uses, pinned so the same inputs give the same bytes on any
x86-64 CPU with AVX2 (docs/guide/errors.md, *The same command gives the same bytes*).

torch, OpenBLAS, MKL and numpy choose their kernels by CPU at run time (AVX-512 on one machine, AVX2 on
another) and by thread count; their last-bit differences are amplified by L-BFGS into different
networks. On the first import of any workbench package (``cosim``, ``controllers``, ``plant_fmu``) --
which must come before torch and numpy are imported, their kernel choice is made at their import --
:func:`pin` sets in ``os.environ``:

* ``ATEN_CPU_CAPABILITY=avx2`` -- torch's vectorised CPU kernels (else AVX-512 where the CPU has it);
* ``OPENBLAS_CORETYPE=Haswell`` -- OpenBLAS's (numpy's and scipy's BLAS) kernels: its AVX2 ones;
* ``MKL_CBWR=COMPATIBLE`` -- MKL's conditional numerical reproducibility, where torch uses MKL;
* ``OMP_NUM_THREADS``, ``OPENBLAS_NUM_THREADS``, ``MKL_NUM_THREADS`` = 1 -- a reduction's order
  depends on its thread count (the trainers also call ``torch.set_num_threads(1)``);
* ``NPY_DISABLE_CPU_FEATURES`` -- numpy's run-time dispatch limited to x86-64-v3 (its AVX-512 paths off).

The values *replace* what the environment had (an inherited ``ATEN_CPU_CAPABILITY=avx512`` would
otherwise make another machine of this one), and child processes -- local dask workers, the isolated
plant processes -- inherit them. ``BUCK_COSIM_NUMERIC_ENV=native`` leaves the environment as it is
(the kernels the libraries choose themselves: faster on some CPUs, bytes that differ between CPUs); the
benchmark suite and the test of this pinning use it. Where torch or numpy was imported before the
workbench (``import torch; import cosim``), their kernels are already chosen: :func:`pin` prints one
warning line naming them, and :func:`late_imports` lets a caller refuse.

On CPUs without AVX2 (or not x86-64: aarch64) the libraries fall back to what the CPU has and the
numbers differ in the last digits; :func:`describe` records what was in force, for the report.

Pinning does not reach every CPU-dependent kernel: ``torch.sqrt`` and ``torch.log`` give other last bits
on AVX-512 CPUs than on AVX2-only ones whatever these settings say (measured with QEMU-emulated CPUs,
cosim/benchmark_harness/cpu_emulation.py); the training avoids them (controllers/lbfgs.py).
"""

from __future__ import annotations

import os
import platform
import sys

#: the escape: this variable set to ``native`` leaves the kernel environment to the libraries
ESCAPE = "BUCK_COSIM_NUMERIC_ENV"
NATIVE = "native"


def _numpy_avx512_features() -> str:
    """numpy's dispatch targets above x86-64-v3 (AVX2, FMA3) in its x86-64 wheels, read from the installed
    version's metadata (numpy is not imported): ``X86_V4 AVX512_ICL AVX512_SPR`` from numpy 2.4 on, the
    single AVX-512 features before (names a build lacks are ignored with an ImportWarning)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        major, minor = (int(part) for part in version("numpy").split(".")[:2])
    except (PackageNotFoundError, ValueError):
        major, minor = 2, 4
    if (major, minor) >= (2, 4):
        return "X86_V4 AVX512_ICL AVX512_SPR"
    return "AVX512F AVX512CD AVX512_KNL AVX512_KNM AVX512_SKX AVX512_CLX AVX512_CNL AVX512_ICL AVX512_SPR"


#: the pinned kernel environment (variable -> value)
PINNED = {
    "ATEN_CPU_CAPABILITY": "avx2",
    "OPENBLAS_CORETYPE": "Haswell",
    "MKL_CBWR": "COMPATIBLE",
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "NPY_DISABLE_CPU_FEATURES": _numpy_avx512_features(),
}
#: libraries whose kernels are chosen when they are imported
KERNEL_LIBRARIES = ("torch", "numpy", "scipy")

_late: tuple[str, ...] = ()
_pinned = False


def native() -> bool:
    """True when ``BUCK_COSIM_NUMERIC_ENV=native`` leaves the kernels to the libraries."""
    return os.environ.get(ESCAPE, "").strip().lower() == NATIVE


def pin() -> tuple[str, ...]:
    """Set :data:`PINNED` in ``os.environ`` (once per process, unless :func:`native`); returns the
    kernel libraries that were imported before, too late to be pinned (one warning line for them)."""
    global _late, _pinned
    if _pinned:
        return _late
    _pinned = True
    if native():
        return ()
    differing = [k for k, v in PINNED.items() if os.environ.get(k) != v]
    _late = tuple(name for name in KERNEL_LIBRARIES if name in sys.modules) if differing else ()
    os.environ.update(PINNED)
    if _late:
        print(f"buck-cosim: warning: {', '.join(_late)} imported before the workbench, so its numeric kernels are "
              f"not pinned and trained models may differ from the committed ones: import cosim first, or set "
              f"{', '.join(differing)} as in cosim/base/numeric_env.py", file=sys.stderr)
    return _late


def late_imports() -> tuple[str, ...]:
    """The kernel libraries imported before :func:`pin` could pin them (empty: pinned in time, or native)."""
    return _late


def kernel_environment() -> dict[str, str | None]:
    """The kernel variables as this process has them (None: unset), and the escape."""
    return {k: os.environ.get(k) for k in (*PINNED, ESCAPE)}


def check_worker_environment(workers: dict) -> str | None:
    """One line naming the dask workers whose kernel environment (``{address: kernel_environment()}``)
    differs from this process's, or None when they all agree."""
    own = kernel_environment()
    bad = {address: {k: v for k, v in env.items() if own.get(k) != v} for address, env in workers.items() if env != own}
    if not bad:
        return None
    address, diff = next(iter(bad.items()))
    shown = ", ".join(f"{k}={v!r} (here {own.get(k)!r})" for k, v in sorted(diff.items()))
    return (f"{len(bad)} dask worker(s) run other numeric kernels than this process, e.g. {address}: {shown}: "
            f"start them from an environment with the settings of cosim/base/numeric_env.py (or `import cosim` "
            f"first in their preload), or set {ESCAPE}={NATIVE} everywhere")


def _cpu_model() -> tuple[str, str, list[str]]:
    """CPU vendor, model name and its SIMD flags (Linux /proc/cpuinfo; platform's otherwise)."""
    vendor, model, flags = "", platform.processor() or platform.machine(), []
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as handle:
            for line in handle:
                key, _, value = line.partition(":")
                key, value = key.strip(), value.strip()
                if key == "vendor_id" and not vendor:
                    vendor = value
                elif key == "model name" and value:
                    model = value
                elif key in ("flags", "Features") and not flags:
                    flags = value.split()
                if key == "" and vendor:
                    break
    except OSError:
        pass
    simd = sorted(f for f in flags if f.startswith(("avx", "fma", "sse4", "amx", "asimd", "sve", "neon")))
    return vendor or platform.machine(), model, simd


def cpu_class(machine: str | None = None, simd: list[str] | None = None) -> str:
    """What the pinned kernels need, in words that are the same on every machine they cover:
    ``x86-64 with AVX2 and FMA`` (Intel and AMD alike), or what the machine lacks."""
    machine = machine or platform.machine()
    if simd is None:
        simd = _cpu_model()[2]
    if machine not in ("x86_64", "AMD64"):
        return f"{machine} (not x86-64: the pinned kernels do not apply; results differ in the last digits)"
    if "avx2" in simd and "fma" in simd:
        return "x86-64 with AVX2 and FMA"
    return "x86-64 without AVX2/FMA (the libraries fall back to older kernels; results differ in the last digits)"


def describe() -> dict:
    """What this process computes with: the kernel settings, the library versions and the kernels they
    chose, the CPU (for the report's numeric-environment section)."""
    import numpy
    import scipy
    import torch

    vendor, model, simd = _cpu_model()
    info = {"pinned": not native() and not _late, "escape": os.environ.get(ESCAPE), "settings": kernel_environment(),
            "late_imports": list(_late), "python": platform.python_version(), "machine": platform.machine(),
            "cpu_vendor": vendor, "cpu_model": model, "cpu_simd_flags": simd,
            "torch": torch.__version__, "torch_cpu_capability": torch.backends.cpu.get_cpu_capability(),
            "torch_threads": torch.get_num_threads(), "numpy": numpy.__version__, "scipy": scipy.__version__}
    try:  # numpy's run-time dispatch targets in use: X86_V3 (AVX2, FMA) when pinned on any AVX2 machine
        from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__

        info["numpy_dispatch_used"] = [t for t in __cpu_dispatch__ if __cpu_features__.get(t)]
    except ImportError:  # another numpy layout
        pass
    info["cpu_class"] = cpu_class(machine=info["machine"], simd=simd)
    return info
