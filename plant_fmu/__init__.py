"""The buck converter plant as an FMI 2.0 FMU (model exchange and co-simulation), built from C sources.

>>> from plant_fmu import fmu_path
>>> path = fmu_path()          # compiles once with fmpy's CMake build, then cached by source hash
"""

from plant_fmu.build import PlantBuildError, export_fmus, fmu_path, source_fmu_path

__all__ = ["PlantBuildError", "export_fmus", "fmu_path", "source_fmu_path"]
