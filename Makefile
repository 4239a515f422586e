# Lamina: the two commands a newcomer needs are `make demo` and `make test`.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
OUT    := out

# numpy's OpenBLAS starts a thread per core for every large product; beside two test
# workers (or the campaign's two processes) those threads fight for the cores: the
# simulator's ray rotations (1.3 M x 3 by 3 x 3) took 0.77 s wall under load with them
# and 0.13 s with one, with identical results. Set it yourself to override.
export OPENBLAS_NUM_THREADS ?= 1

.PHONY: install demo test lint bench tui fuzz arm64-check clean

$(STAMP): shared/pyproject.toml device/pyproject.toml host/pyproject.toml requirements-dev.txt
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else "Lamina needs Python 3.11 or newer; run: make PYTHON=python3.11 ...")'
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	# One command, so pip resolves lamina-shared from this tree rather than a registry.
	$(BIN)/python -m pip install --quiet -e shared -e device -e "host[meshlab]" -r requirements-dev.txt
	touch $@

install: $(STAMP)

# Demo scans go to their own library under out/demo, never into the user's; a re-run
# starts afresh (the scanner itself never overwrites an earlier scan).
DEMO_LIBRARY := --library $(OUT)/demo/library.sqlite
demo: install
	rm -rf $(OUT)/demo
	$(BIN)/lamina scan --device sim --object cylinder:d=19.05 --sections 4 --pitch 2 --views 8 \
		--expect cylinder:d=19.05 $(DEMO_LIBRARY) -o $(OUT)/demo/cylinder
	$(BIN)/lamina scan --device sim --object ellipsoid:a=10,b=6.5,c=20,z=-1 --sections 10 \
		--pitch 2 --views 8 --expect ellipsoid:a=10,b=6.5,c=20,z=-1 $(DEMO_LIBRARY) \
		-o $(OUT)/demo/oval-cap

# The slowest tests are listed at the end, so the 15-minute budget can be kept in view.
# Two worker processes (one per core); a test file stays in one worker, so a module's
# scan fixture runs once.
test: install
	$(BIN)/python -m pytest -q -n 2 --dist loadfile --durations=25

lint: install
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy shared/lamina_shared device/lamina_device host/lamina_host
	$(BIN)/lint-imports --no-logo

# The terminal UI on the simulated scanner (add DEVICE=/dev/ttyACM0 for a real one).
DEVICE ?= sim
tui: install
	$(BIN)/lamina tui --device $(DEVICE)

bench: install
	$(BIN)/python tests/benchmarks/run.py --out $(OUT)/bench.json

# The normal suite runs a short fuzz; this runs the same properties with many more examples,
# and LIBRARY_RUNS schedules of processes sharing one scan library (figures, one JSON line a
# run, in out/library-fuzz.jsonl).
LIBRARY_RUNS ?= 100
fuzz: install
	LAMINA_FUZZ_EXAMPLES=20000 $(BIN)/python -m pytest -q tests/test_fuzz.py
	mkdir -p $(OUT)
	LAMINA_LIBRARY_RUNS=$(LIBRARY_RUNS) LAMINA_LIBRARY_LOG=$(OUT)/library-fuzz.jsonl \
		$(BIN)/python -m pytest -q tests/test_library_concurrency.py

# The host and device on an arm64 Debian Bookworm userland under qemu (root; debootstrap and
# qemu-user-static): installs, a short simulated scan and the device's tests. Takes long the
# first time (the userland is cached in ~/.cache/lamina-arm64); not part of `make test`.
arm64-check:
	hardware/arm64-check.sh

clean:
	rm -rf $(VENV) $(OUT)
	rm -rf shared/build device/build host/build */*.egg-info
