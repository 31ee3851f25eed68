"""The closed loop as an SSP package: the scenario as an FMU, SSP 1.0 export, and running an SSP.

* :mod:`cosim.ssp.scenario_source` -- a scenario as a signal-source FMU (hand-written C over the
  plant's FMI glue, one generated header of data);
* :mod:`cosim.ssp.package` -- the SSP 1.0 archive: writing it (``export-ssp``), validating it
  against the SSP 1.0 schemas and reading it back;
* :mod:`cosim.ssp.engines` -- running it with the workbench's master, with fmpy's SSP simulation
  and with libcosim, each result a workbench run table (``run-ssp``).

Layer: with the core (it uses the master, the scenarios and the FMU adapters); the study and the
command line sit above it.
"""
