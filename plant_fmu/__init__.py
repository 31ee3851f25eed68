"""The buck converter plant as an FMI 2.0 FMU (model exchange and co-simulation), built from C sources,
and its FMI 3.0 edition (the same model code behind the FMI 3.0 glue).

>>> from plant_fmu import fmu_path
>>> path = fmu_path()          # compiles once with fmpy's CMake build, then cached by source hash
>>> path3 = fmu_path(fmi_version=3)
"""

from cosim.base.numeric_env import pin as _pin_numeric_kernels

_pin_numeric_kernels()  # before torch or numpy is imported (cosim/base/numeric_env.py)

from plant_fmu.build import PlantBuildError, export_fmus, fmu_path, source_fmu_path  # noqa: E402

__all__ = ["PlantBuildError", "export_fmus", "fmu_path", "source_fmu_path"]
