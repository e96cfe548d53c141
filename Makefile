# The two set-up commands: `make demo` (the bundled default scene) and `make test`.
# Both create the virtual environment on first use. DOLFINX=system uses Debian's DOLFINx.
VENV    ?= .venv
DOLFINX ?= wheel
PY      := $(VENV)/bin/python
# The wheel ships MPICH's mpiexec in the venv; Debian's DOLFINx uses the system one.
MPIEXEC  = $$([ -x $(VENV)/bin/mpiexec ] && echo $(VENV)/bin/mpiexec || echo mpiexec)
STAMP   := $(VENV)/.lungmech-installed

.PHONY: demo test lint test-serial test-mpi bench bench-rom bench-rom-bases bench-ecsw bench-registration bench-layout bench-rom-parameters clean

$(STAMP): pyproject.toml
	DOLFINX=$(DOLFINX) bash .ci/make-venv $(VENV)
	touch $@

demo: $(STAMP)
	$(VENV)/bin/lungmech run -o results/default

test: lint test-serial test-mpi

# ruff's linter and formatter, configured in pyproject.toml.
lint: $(STAMP)
	$(VENV)/bin/ruff check lungmech tests demos benchmarks
	$(VENV)/bin/ruff format --check lungmech tests demos benchmarks

# Two workers (pytest-xdist) on the two cores CI has; the slowest tests are listed at the end.
test-serial: $(STAMP)
	$(PY) -m pytest -m "not mpi" -n 2 --dist worksteal --durations=12 tests

test-mpi: $(STAMP)
	# A test failing on one rank only would leave the other waiting: bound the run.
	timeout 1200 $(MPIEXEC) -n 2 $(PY) -m pytest -m mpi -p no:cacheprovider tests

bench: $(STAMP)
	$(PY) benchmarks/run.py

# The real-time lung: hyper-reduced over a 3-parameter box at three mesh sizes, to 104k dofs (3 h).
bench-rom: $(STAMP)
	$(PY) benchmarks/rom_real_time.py

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

bench-layout: $(STAMP)
	$(PY) benchmarks/layout.py

clean:
	rm -rf results benchmarks/results
