# Two set-up commands for a fresh machine: `make demo` and `make test`.
# Both create .venv, install torch's CPU build first (a bare `torch` would pull
# a multi-GB CUDA build), then the project in editable mode.

PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
RELIGHT := $(VENV)/bin/relight
STAMP  := $(VENV)/.installed-stamp

.PHONY: install demo test test-fast man benchmarks clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e '.[test]'
	touch $(STAMP)

install: $(STAMP)

# The main job on built-in data; results under demo/.
demo: install
	mkdir -p demo
	$(RELIGHT) envmap builtin:sky --to latlong --size 32x16 -o demo/sky_32x16.exr --preview demo/sky.png
	$(RELIGHT) envmap builtin:studio --to cube --size 64 -o demo/studio_cube.exr --preview demo/studio_cube.png
	$(RELIGHT) envmap builtin:point --size 64x32 -o demo/point.exr
	$(RELIGHT) envmap demo/studio_cube.exr --info -o demo/studio_info.json
	@echo "demo outputs are in demo/"

test: install
	$(PY) -m pytest

man: install
	$(PY) -m relight_cli.manpage man

benchmarks: install
	@for b in benchmarks/bench_*.py; do echo "== $$b"; $(PY) $$b || exit 1; done

clean:
	rm -rf demo build *.egg-info .pytest_cache
