"""buck-cosim: an FMU co-simulation workbench for buck-converter control.

The public names, importable from here (docs/guide/python-controller.md):

* ``Measurement``, ``Controller`` -- what a controller sees at a sample, and the protocol it
  implements (``name``, ``sample_period`` [s], ``duty_limits``, ``reset()``, ``step(m)``,
  ``describe()``);
* ``PIController`` -- the workbench's PI (gains in 1/V and 1/(V s));
* ``builtin_binding(mode)`` -- the project's plant FMU, ``"averaged"`` or ``"switched"``;
  ``load_binding(path)`` -- an external plant FMU through a binding file;
* ``load_scenario(name_or_path)`` -- a shipped scenario or a scenario file;
* ``simulate(binding, controller, scenario)`` -- one closed-loop run -> ``RunResult`` (``.frame``:
  the pandas table, ``.metadata``, ``.complete``);
* ``run_metrics(result)`` -- rise time, overshoot, settling, IAE, ... of a run;
  ``write_run`` / ``read_run`` -- CSV and Parquet with metadata;
* ``plot_scenario(results, stem)`` -- the run figure of one or more runs (PNG + SVG);
* ``open_controller(path)`` -- a controller FMU (or controller-binding file) as a controller.

They are looked up on first use, so ``import cosim`` stays cheap (no torch, no FMU build). Importing
any workbench package first pins the numeric kernels of torch, numpy and BLAS for this process and its
children (:mod:`cosim.base.numeric_env`), so training gives the same bytes on every x86-64 CPU with AVX2.
"""

from __future__ import annotations

from cosim.base.numeric_env import pin as _pin_numeric_kernels

_pin_numeric_kernels()  # before torch or numpy is imported (cosim/base/numeric_env.py)

__all__ = ["Controller", "Measurement", "PIController", "RunResult", "builtin_binding", "load_binding",
           "load_scenario", "open_controller", "plot_scenario", "read_run", "run_metrics", "simulate", "write_run"]


def __getattr__(name: str):
    if name in ("Controller", "Measurement"):
        from controllers.base import Controller, Measurement

        return {"Controller": Controller, "Measurement": Measurement}[name]
    if name == "PIController":
        from controllers.pi import PIController

        return PIController
    if name == "builtin_binding":
        from cosim.fmi.binding import builtin_binding

        return builtin_binding
    if name == "load_binding":
        from cosim.fmi.binding_file import load_binding

        return load_binding
    if name == "open_controller":
        from cosim.fmi.controller import open_controller

        return open_controller
    if name == "load_scenario":
        from cosim.scenarios import load_scenario

        return load_scenario
    if name == "simulate":
        from cosim.master import simulate

        return simulate
    if name == "run_metrics":
        from cosim.metrics import run_metrics

        return run_metrics
    if name == "plot_scenario":
        from cosim.plots import plot_scenario

        return plot_scenario
    if name in ("RunResult", "read_run", "write_run"):
        from cosim.results import RunResult, read_run, write_run

        return {"RunResult": RunResult, "read_run": read_run, "write_run": write_run}[name]
    raise AttributeError(f"module 'cosim' has no attribute {name!r}")


def __dir__():
    return sorted(__all__)
