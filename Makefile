# The two set-up commands: `make demo` (the bundled default scene) and `make test`.
# Both create the virtual environment on first use, at the tested versions of
# requirements/lock.txt. DOLFINX=system uses Debian's DOLFINx (and Debian's versions).
# `make test-latest` tests the newest versions pyproject.toml allows (in .venv-latest);
# `make lock` then writes them to the lock.
VENV    ?= .venv
DOLFINX ?= wheel
PY      := $(VENV)/bin/python
# The wheel ships MPICH's mpiexec in the venv; Debian's DOLFINx uses the system one.
MPIEXEC  = $$([ -x $(VENV)/bin/mpiexec ] && echo $(VENV)/bin/mpiexec || echo mpiexec)
STAMP   := $(VENV)/.lungmech-installed
LOCK    ?= requirements/lock.txt
# The suite starts hundreds of Python processes (the CLI, demos, benchmarks, MPI ranks). Where
# PYTHONDONTWRITEBYTECODE is set, each compiles lungmech's sources again (about 0.7 s of CPU
# apiece, 27 s in a run of the suite): let them keep their bytecode (__pycache__, ignored by git).
unexport PYTHONDONTWRITEBYTECODE

.PHONY: demo docs docs-check test test-quick test-latest test-long lock lint test-serial test-mpi test-mpi-all bench bench-quick bench-rom bench-rom-imaged bench-rom-bases bench-ecsw bench-registration bench-layout bench-rom-parameters bench-ensemble bench-trade bench-greedy-batch bench-threads bench-twin bench-population bench-twin-population bench-pgd bench-pgd-tangent clean

$(STAMP): pyproject.toml $(wildcard $(LOCK))
	DOLFINX=$(DOLFINX) LOCK=$(LOCK) bash .ci/make-venv $(VENV)
	touch $@

demo: $(STAMP)
	$(VENV)/bin/lungmech run -o results/default

test: lint test-serial test-mpi

# The documentation site (Sphinx, MyST pages, the API reference from the docstrings) into
# docs/_build/html; a warning is an error.
docs: $(STAMP)
	$(VENV)/bin/sphinx-build -W --keep-going -q -b html docs docs/_build/html
	@echo "docs: open docs/_build/html/index.html"

# Every page of the built site in headless Chromium (the system's: apt-get install chromium):
# console errors, resources and images that do not load, broken internal links; screenshots.
docs-check: docs
	$(PY) docs/check_site.py docs/_build/html

# The newest versions pyproject.toml allows, in their own venv; run it before `make lock`.
# LUNGMECH_UNLOCKED tells the suite's version check that these are not the locked versions.
test-latest:
	rm -f .venv-latest/.lungmech-installed
	$(MAKE) test VENV=.venv-latest LOCK=none LUNGMECH_UNLOCKED=1

lock:
	bash .ci/lock .venv-latest

# ruff's linter and formatter, and mypy on the whole package (configured in
# pyproject.toml): every module checked, with disallow_untyped_defs. mypy keeps its cache beside
# FFCx's JIT cache, in the user's cache folder, so that a fresh clone checks in a second instead
# of 40 (its entries are checked against each file's contents: any clone, any commit).
TYPED = lungmech
MYPY_CACHE ?= $${XDG_CACHE_HOME:-$$HOME/.cache}/lungmech/mypy
lint: $(STAMP)
	$(VENV)/bin/ruff check lungmech tests demos benchmarks docs
	$(VENV)/bin/ruff format --check lungmech tests demos benchmarks docs
	$(VENV)/bin/mypy --cache-dir "$(MYPY_CACHE)" $(TYPED)

# One rank, two workers (pytest-xdist) on the two cores CI has; the tests marked mpi (several
# ranks only) are left out by tests/conftest.py. The slowest are listed at the end.
test-serial: $(STAMP)
	$(PY) -m pytest -m "not long" -n 2 --dist worksteal --durations=12 tests

# The edit–test loop: the tests that take under a second each (not slow), one rank, two
# workers; with a warm JIT cache under two minutes. make test runs them all.
test-quick: $(STAMP)
	$(PY) -m pytest -m "not long and not slow" -n 2 --dist worksteal -q -p no:cacheprovider tests

# The cases too long for the suite's budget (registrations of realistic lungs at 1 mm voxels),
# on one rank and, those marked mpi too, on two.
test-long: $(STAMP)
	$(PY) -m pytest -m long -n 2 --durations=12 tests
	bash .ci/test-mpi $(MPIEXEC) $(PY) "long and mpi" $$(grep -l 'mark\.mpi' tests/test_*.py | xargs grep -l 'mark\.long')

# The mpi tests on two ranks (each compares a 2-rank result with one rank's), in groups of
# files (.ci/test-mpi says why). make test runs these; test-mpi-all adds every test not slow
# (the cheap part of the suite on two ranks, about 5 minutes more: outside make test's budget),
# the tests marked serial left out (tests/conftest.py). test-mpi starts only the files that name
# the marker (mark.mpi): a file without an mpi test would start ranks for nothing.
test-mpi: $(STAMP)
	bash .ci/test-mpi $(MPIEXEC) $(PY) "not long and mpi" $$(grep -l 'mark\.mpi' tests/test_*.py)

test-mpi-all: $(STAMP)
	bash .ci/test-mpi $(MPIEXEC) $(PY) "not long and (mpi or not slow)"

bench: $(STAMP)
	$(PY) benchmarks/run.py

# Every benchmark's --quick case (about 4 minutes), as the suite runs them: results in a
# temporary folder, benchmarks/results untouched.
bench-quick: $(STAMP)
	$(PY) -m pytest -n 2 -p no:cacheprovider tests/test_benchmarks.py

# The real-time lung: hyper-reduced over a 3-parameter box at three mesh sizes, to 104k dofs (3 h).
bench-rom: $(STAMP)
	$(PY) benchmarks/rom_real_time.py

# The real-time lung at every μ: its reference found on the image at each point, at the bundled
# mesh and h = 8 mm (about 1 h).
bench-rom-imaged: $(STAMP)
	$(PY) benchmarks/rom_imaged.py

# Every basis kind and size, Galerkin (no hyper-reduction), on the breathing lung.
bench-rom-bases: $(STAMP)
	$(PY) benchmarks/rom.py

bench-ecsw: $(STAMP)
	$(PY) benchmarks/ecsw_block.py
	$(PY) benchmarks/ecsw_lung.py

bench-registration: $(STAMP)
	$(PY) benchmarks/registration.py

# Memory and time of the canonical dof layout on 1 and 2 ranks (starts mpiexec itself).
bench-rom-parameters: $(STAMP)
	$(PY) benchmarks/rom_parameters.py

# The bundled lung's speed–accuracy trade, by lungmech trade itself (about 1.5 h; resumable).
bench-trade: $(STAMP)
	$(PY) benchmarks/trade.py

# Many full solves serially, in 2 groups of 1 rank and on Parsl's 2 local workers: throughput.
bench-ensemble: $(STAMP)
	$(PY) benchmarks/ensemble.py

# A greedy adding 2 full solves a round, in this process and on Parsl's 2 workers, against 1.
bench-greedy-batch: $(STAMP)
	$(PY) benchmarks/greedy_batch.py

# An offline build with 1 BLAS thread and with the machine's, quiet and under a load of 4.
bench-threads: $(STAMP)
	$(PY) benchmarks/threads.py

bench-layout: $(STAMP)
	$(PY) benchmarks/layout.py

# Twin experiments: 3 synthetic patients, supine/prone/both, noise 0–40 %, against Nelder–Mead (about an hour).
bench-twin: $(STAMP)
	$(PY) benchmarks/twin.py

# One reduced model for 26 synthetic patients' shapes, against the full model at 6 held out (about 1.5 h).
bench-population: $(STAMP)
	$(PY) benchmarks/population.py

# The twin experiments' right lungs personalised on a population's model and on models of their own.
bench-twin-population: $(STAMP)
	$(PY) benchmarks/twin_population.py

# The a priori PGD beside the full and a hyper-reduced model: NeuROM's anchor plate and a lung phantom.
bench-pgd: $(STAMP)
	$(PY) benchmarks/pgd.py

# Why the a priori PGD of a balanced lung takes each point's tangent: Newton at points of the box with fixed tangents.
bench-pgd-tangent: $(STAMP)
	$(PY) benchmarks/pgd_tangent.py

clean:
	rm -rf results benchmarks/results
