"""The numeric kernels are pinned for the whole process tree (cosim/base/numeric_env.py): the same
identification, distillation and seed job give the same bytes whatever kernel environment a process
inherits -- the stand-in, on one machine, for CPUs that choose other kernels (README, *Same bytes on
every machine*)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from cosim.base import numeric_env
from cosim.base.errors import ConfigError
from cosim.study.vocabulary import PAPER_SPEC

ROOT = Path(__file__).resolve().parents[1]
JOB = Path(__file__).with_name("numeric_env_job.py")
#: the artefacts compared: the identified network, the distilled policy, the seed job's metrics and summary
ARTEFACTS = ("identified.pt", "policy.pt", "metrics/metrics__nominal-averaged__1ms__seed1.csv",
             "pipelines/nominal-averaged__1ms__seed1.json")
#: kernel environments a process may inherit: torch's generic / AVX2 / AVX-512 kernels, OpenBLAS's
#: Skylake-X / Haswell kernels, MKL's AVX2 branch
ENVIRONMENTS = {
    "default": {"ATEN_CPU_CAPABILITY": "default", "OPENBLAS_CORETYPE": "SkylakeX"},
    "avx2": {"ATEN_CPU_CAPABILITY": "avx2", "OPENBLAS_CORETYPE": "Haswell", "MKL_CBWR": "AVX2"},
    "avx512": {"ATEN_CPU_CAPABILITY": "avx512", "OPENBLAS_CORETYPE": "SkylakeX", "OMP_NUM_THREADS": "2"},
}
TIMEOUT = 600  # [s] for all the jobs together (about 20 s each, two at a time on two cores)
EMULATED_TIMEOUT = 1200  # [s] the training under QEMU (about 3 min on an idle core: it emulates every instruction)


def cpu_has_avx512() -> bool:
    """Whether this (Linux) machine's CPU has AVX-512 (the flag avx512f in /proc/cpuinfo)."""
    try:
        return " avx512f" in Path("/proc/cpuinfo").read_text()
    except OSError:
        return False


def native_environment() -> dict:
    """The default environment as a process left native inherits it. On a CPU without AVX-512 OpenBLAS is not
    forced onto its Skylake-X kernels: unpinned, it would run them and die of an illegal instruction (SIGILL,
    measured on an AMD EPYC with AVX2 only); the generic torch kernels still differ from the pinned AVX2 ones."""
    if cpu_has_avx512():
        return dict(ENVIRONMENTS["default"])
    return {k: v for k, v in ENVIRONMENTS["default"].items() if k != "OPENBLAS_CORETYPE"}


def _environment(extra: dict) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in (*numeric_env.PINNED, numeric_env.ESCAPE)}
    return {**env, "PYTHONPATH": str(ROOT), **extra}


def _python(code: str, extra: dict) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], env=_environment(extra), capture_output=True, text=True,
                          timeout=120, cwd=ROOT)


@pytest.fixture(scope="module")
def artefacts(tmp_path_factory) -> dict[str, dict[str, bytes]]:
    """Each environment's artefacts (pinned), and those of the default one left native (the old behaviour)."""
    root = tmp_path_factory.mktemp("kernels")
    runs = {name: extra for name, extra in ENVIRONMENTS.items()}
    runs["native"] = {**native_environment(), numeric_env.ESCAPE: numeric_env.NATIVE}
    processes = {}
    for name, extra in runs.items():
        log = (root / f"{name}.log").open("w")
        processes[name] = subprocess.Popen([sys.executable, str(JOB), str(root / name)], env=_environment(extra),
                                           stdout=log, stderr=subprocess.STDOUT, cwd=ROOT)
        log.close()
        if len(processes) % 2 == 0:  # two at a time
            for process in processes.values():
                process.wait(timeout=TIMEOUT)
    out = {}
    for name, process in processes.items():
        process.wait(timeout=TIMEOUT)
        assert process.returncode == 0, f"{name}: {(root / f'{name}.log').read_text()[-2000:]}"
        out[name] = {a: (root / name / a).read_bytes() for a in ARTEFACTS}
    return out


def test_identification_distillation_and_seed_job_write_the_same_bytes_in_every_kernel_environment(artefacts):
    reference = artefacts["default"]
    for name in ENVIRONMENTS:
        for artefact in ARTEFACTS:
            assert artefacts[name][artefact] == reference[artefact], f"{artefact} differs under {name}"


#: what the native kernels change on this machine: the trained networks and the seed job's summary (its network's
#: held-out errors). Its metrics table may come out the same: at 1 ms the NNPC's optimizer (the RTI) rounds the duty
#: to the search's finest step (1/10240), which networks apart in their last bits mostly command alike
CHANGED_BY_NATIVE_KERNELS = ("identified.pt", "policy.pt", "pipelines/nominal-averaged__1ms__seed1.json")


def test_the_environments_do_change_the_bytes_when_the_kernels_are_left_native(artefacts):
    """What the pinning prevents, on this machine: the default kernels train other networks."""
    for artefact in CHANGED_BY_NATIVE_KERNELS:
        assert artefacts["native"][artefact] != artefacts["default"][artefact], artefact


@pytest.mark.emulated
def test_training_writes_the_same_bytes_on_an_emulated_cpu_of_another_kind(tmp_path):
    """The NN training on another x86-64 CPU -- QEMU user mode answering CPUID as an AVX2-only Intel Haswell
    (or, on a host without AVX-512, as the other vendor's AVX2 CPU) -- writes the host's bytes. Failed
    before controllers/lbfgs.py: torch's line search took torch.sqrt, whose last bits depend on the CPU."""
    from cosim.benchmark_harness import cpu_emulation
    from cosim.design.data_collection import collect
    from cosim.design.identification import collection_settings
    from cosim.design.vocabulary import PAPER_PERIOD
    from cosim.study.reproduce import FULL, Pipeline, _tuned

    pipeline = Pipeline("nominal", "averaged", PAPER_PERIOD)
    pi = _tuned(pipeline, tmp_path, FULL)
    data = tmp_path / "data.parquet"
    settings = collection_settings(PAPER_PERIOD, FULL.samples, 2, spec=PAPER_SPEC)
    collect(pipeline.binding(), pi.controller(), settings).to_parquet(data)
    env = _environment({})
    job = [sys.executable, str(JOB), "train", str(data)]
    here = subprocess.run([*job, str(tmp_path / "host")], env=env, capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert here.returncode == 0, here.stderr[-2000:]
    model = cpu_emulation.contrasting_model()
    there = subprocess.run(cpu_emulation.command([*job, str(tmp_path / "emulated")], model), env=env,
                           capture_output=True, text=True, timeout=EMULATED_TIMEOUT, cwd=ROOT)
    assert there.returncode == 0, there.stderr[-2000:]
    assert (tmp_path / "emulated" / "trained.pt").read_bytes() == (tmp_path / "host" / "trained.pt").read_bytes(), (
        f"the network trained on an emulated {cpu_emulation.DESCRIPTIONS[model]} differs from this machine's")


def test_a_workbench_process_runs_the_pinned_kernels_whatever_it_inherits():
    code = ("import cosim, os, torch, numpy; from numpy._core._multiarray_umath import __cpu_features__ as f; "
            "print(torch.backends.cpu.get_cpu_capability(), os.environ['OPENBLAS_CORETYPE'], "
            "os.environ['MKL_NUM_THREADS'], f['AVX512_SPR'])")
    pinned = _python(code, {"ATEN_CPU_CAPABILITY": "avx512", "OPENBLAS_CORETYPE": "SkylakeX", "MKL_NUM_THREADS": "4"})
    assert pinned.returncode == 0 and pinned.stderr == ""
    assert pinned.stdout.split() == ["AVX2", "Haswell", "1", "False"]
    native = _python(code, {"ATEN_CPU_CAPABILITY": "default", "OPENBLAS_CORETYPE": "SkylakeX", "MKL_NUM_THREADS": "4",
                            numeric_env.ESCAPE: "native"})
    assert native.returncode == 0 and native.stdout.split()[:3] == ["DEFAULT", "SkylakeX", "4"]


def test_torch_imported_before_the_workbench_is_named_in_one_warning_line():
    late = _python("import torch, cosim; from cosim.base.numeric_env import late_imports; print(late_imports())", {})
    assert late.returncode == 0 and late.stdout.strip() == "('torch', 'numpy')"
    lines = late.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("buck-cosim: warning: torch, numpy imported before the workbench")
    inherited = _python("import torch, cosim", dict(numeric_env.PINNED))  # a child: the environment is pinned already
    assert inherited.returncode == 0 and inherited.stderr == ""


def test_workers_with_other_kernels_are_named_in_one_line():
    own = numeric_env.kernel_environment()
    assert numeric_env.check_worker_environment({"tcp://a:1": dict(own)}) is None
    line = numeric_env.check_worker_environment({"tcp://a:1": own, "tcp://b:2": {**own, "ATEN_CPU_CAPABILITY": "avx512"}})
    assert "\n" not in line and line.startswith("1 dask worker(s) run other numeric kernels than this process, e.g. "
                                                "tcp://b:2: ATEN_CPU_CAPABILITY='avx512' (here 'avx2')")


def test_a_cluster_whose_worker_runs_other_kernels_is_refused_before_any_work():
    import dask

    from cosim.design.cluster import dask_client

    # a worker told to keep its own kernels (an inherited ATEN_CPU_CAPABILITY alone is re-pinned when the
    # worker imports the workbench, before torch: that worker computes the same bytes and is accepted)
    other = {"ATEN_CPU_CAPABILITY": "avx512", numeric_env.ESCAPE: "native"}
    with dask.config.set({"distributed.nanny.environ": other}):
        with pytest.raises(ConfigError, match=r"1 dask worker\(s\) run other numeric kernels .*"
                                              r"BUCK_COSIM_NUMERIC_ENV='native' \(here None\)"):
            with dask_client(workers=1):
                pytest.fail("the client was handed out")
    with dask_client(workers=1) as client:  # local workers inherit the pinned environment
        assert client.submit(os.environ.get, "ATEN_CPU_CAPABILITY").result(timeout=60) == "avx2"
