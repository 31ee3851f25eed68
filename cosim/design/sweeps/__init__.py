"""Sweeps and Monte Carlo studies on dask: tolerance studies that run on one laptop or a cluster.

One module per responsibility, in the order a sweep uses them:

* :mod:`~cosim.design.sweeps.spec` -- the sweep file (TOML), parsed and checked with file, key and line;
* :mod:`~cosim.design.sweeps.plan` -- the file against its plant, expanded into runs with content-hash ids;
* :mod:`~cosim.design.sweeps.designs` -- the controllers, designed once on the nominal plant;
* :mod:`~cosim.design.sweeps.recipes` -- what crosses to the workers (FMU and model bytes, settings);
* :mod:`~cosim.design.sweeps.worker` -- a task on a worker: a batch of runs on one reused FMU instance;
* :mod:`~cosim.design.sweeps.execute` -- the tasks on a dask cluster, parts written as they finish;
* :mod:`~cosim.design.sweeps.dataset` -- the partitioned Parquet dataset and the sweep's manifest;
* :mod:`~cosim.design.sweeps.summary` -- SWEEP.md, the yield and the figures;
* :mod:`~cosim.design.sweeps.sweep` -- ``buck-cosim sweep`` end to end.

``studies/`` holds the shipped sweep files (``buck-cosim sweep tolerance``): they install with the
package, like the shipped scenarios, so a user has a working example wherever the workbench runs.
"""
