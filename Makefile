# The two commands of the README. Each creates .venv and installs everything it needs.
.PHONY: reproduce test bench bootstrap docs every-seed examples

bootstrap:
	@bash scripts/bootstrap.sh

# Main job: the whole paper reproduction, writing results/, then the same study for the second converter (the 24 V ->
# 5 V point-of-load buck of examples/pol_buck/) on the workbench's C plant, writing results/pol-buck/ (about a
# minute), and as a third-party pythonfmu FMU, writing results/pol-buck-pythonfmu/ (about five: a Python FMU).
reproduce: bootstrap examples
	.venv/bin/buck-cosim reproduce
	.venv/bin/buck-cosim study --plant examples/pol_buck/pol_builtin.toml --out results/pol-buck
	.venv/bin/buck-cosim study --plant examples/pol_buck/pol_pythonfmu.toml --out results/pol-buck-pythonfmu

# The test suite (what CI runs), its files shared between up to two processes (pytest-xdist; one per core on a
# single-core machine): about 15 minutes on two cores, 23 run one after another. A test file stays in one process
# (--dist loadfile), so its module fixtures are made once; session fixtures are made once per process.
test: bootstrap
	.venv/bin/python -m pytest -q -n auto --maxprocesses 2 --dist loadfile

# Benchmarks (not run by CI; a smoke test runs each once on a tiny size).
bench: bootstrap
	.venv/bin/buck-cosim bench

# The documentation site, built with --strict into site/ (docs/, mkdocs.yml).
docs: bootstrap
	NO_MKDOCS_2_WARNING=1 .venv/bin/python -m mkdocs build --strict

# Every identification seed, beyond the reproduction's seed 0 (needs make reproduce's results first):
# the RTI against the search, both plants, both rates (issue 24's quality targets): results/optimizer-every-seed.csv
# and .md (9 minutes on two cores on a first run, which identifies the seeds' networks and caches them; 3 after); the
# explicit NNPC distilled from every seed's NNPC against it at one switching period: results/explicit-every-seed.csv
# and .md (6 minutes on a first run: twelve distillations of about 40 s each on a shared core, cached; under a
# minute after), and the same with the search's labels instead of the RTI's: explicit-every-seed-search-labels.*
# (10 minutes on a first run: fifteen distillations, seed 0's too).
every-seed: bootstrap
	nice .venv/bin/python scripts/optimizer_every_seed.py --results results --out results
	nice .venv/bin/python scripts/explicit_every_seed.py --results results --out results
	nice .venv/bin/python scripts/explicit_every_seed.py --results results --out results --expert-optimizer search

# The second converter's FMUs (examples/pol_buck/): the workbench's C plant and the pythonfmu one, into build/ there
# (the pythonfmu build made reproducible: the same sources give the same bytes, so the study's results do too).
examples: bootstrap
	.venv/bin/buck-cosim build-fmu --output examples/pol_buck/build
	.venv/bin/pythonfmu build -f examples/pol_buck/pol_buck.py -d examples/pol_buck/build
	.venv/bin/python scripts/reproducible_fmu.py examples/pol_buck/build/PolBuck.fmu
