"""Open a plant FMU: check the archive, choose its interface, and step it in this process (the FMI
2.0 or 3.0 adapter, :mod:`cosim.fmi.plant_fmi2` / :mod:`cosim.fmi.plant_fmi3`) or in a child
process (:class:`cosim.fmi.isolation.IsolatedPlant`). The master sees only the methods of
:class:`cosim.fmi.plant_fmi2.FmuPlant`, whichever it gets.
"""

from __future__ import annotations

from dataclasses import replace

from cosim.fmi.archive import check_fmu
from cosim.fmi.binding import PlantBinding
from cosim.fmi.isolation import IsolatedPlant, isolation_possible, open_in_process
from cosim.fmi.plant_fmi2 import FmuPlant, choose_interface, normalise_interface


def open_plant(binding: PlantBinding, interface: str | None = None, relative_tolerance: float = 1e-8,
               instance_name: str = "plant", *, isolate: bool | None = None, unzip_dir: str | None = None) -> FmuPlant:
    """Check the binding's FMU, choose its interface (``interface``, else the binding's, else
    co-simulation when offered) and instantiate it. ``relative_tolerance`` is CVode's (model exchange).

    ``isolate``: step the FMU in a child process (:class:`cosim.fmi.isolation.IsolatedPlant`), so a
    crash inside it, or a step that exceeds its wall-time limit, ends the run with an error instead
    of taking the workbench with it (default: the binding's ``isolate``, which binding files turn
    on). A daemonic process (dask's default worker) cannot start that child: there the FMU is
    stepped in this process (:func:`cosim.fmi.isolation.isolation_possible`), and the plant's
    binding says so (``isolate`` false, so a run's metadata states what was run).
    ``unzip_dir``: an empty folder to extract the FMU into (default: a new temporary one).
    """
    checked = check_fmu(binding.fmu_path)
    chosen = choose_interface(checked, normalise_interface(interface or binding.interface), binding.origin)
    if binding.isolate if isolate is None else isolate:
        if isolation_possible():
            return IsolatedPlant(binding, checked, chosen, relative_tolerance=relative_tolerance,
                                 instance_name=instance_name)
    if binding.isolate:
        binding = replace(binding, isolate=False)
    return open_in_process(binding, checked, chosen, relative_tolerance, instance_name, unzip_dir)
