# The set-up targets of the README and docs/install.md. Each creates/refreshes .venv from scratch on a fresh machine.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip
STAMP := $(VENV)/.installed-$(shell cat pyproject.toml constraints.txt | cksum | cut -d' ' -f1)
# The pytest workers share one Warp kernel cache (see tests/conftest.py); the 25 slowest tests are listed at the end.
PYTEST_ARGS ?= -n 2 --dist loadgroup --durations=25

.PHONY: demo test bench fuzz install docs clean

$(PY):
	$(PYTHON) -m venv $(VENV)

$(STAMP): $(PY) pyproject.toml constraints.txt
	$(PIP) install -c constraints.txt torch==2.13.0
	$(PIP) install -c constraints.txt -e '.[test,bench,docs]'
	rm -f $(VENV)/.installed-* && touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(PY) -m scenes tunnel --out tunnel.rrd --iters 500
	$(PY) benchmarks/inverse.py --scenes tunnel --seeds 4 --iters 500 --out tunnel_loss
	$(PY) -m scenes bank_shot --out bank_shot.rrd --start miss --iters 300
	$(PY) -m scenes billiards --out billiards.rrd --start seeded --seed 0 --methods proposed,baseline --optimizer adam --plot billiards_loss.png
	$(PY) -m scenes paper_cubic --out paper_cubic.rrd
	$(PY) -m scenes paper_quadratic --out paper_quadratic.rrd
	$(PY) -m scenes cloth_rigid --out cloth_rigid.rrd --steps 240

test: $(STAMP)
	$(PY) -m pytest $(PYTEST_ARGS)

bench: $(STAMP)
	$(PIP) install -c constraints.txt -e '.[difftaichi]'
	$(PY) benchmarks/roots.py
	$(PY) benchmarks/ccd.py --max-iterations 1000000 --generated --mesh
	$(PY) benchmarks/sim.py
	$(PY) benchmarks/implicit_accuracy.py
	$(PY) benchmarks/rollout.py
	$(PY) benchmarks/grazing.py
	$(PY) benchmarks/orthogonal_clamp.py
	$(PY) benchmarks/inverse.py
	$(PY) benchmarks/billiards.py

fuzz: $(STAMP)
	$(PY) benchmarks/fuzz_roots.py

docs: $(STAMP)
	$(PY) -m mkdocs build --strict --site-dir site

clean:
	rm -rf $(VENV) *.rrd .pytest_cache .warp_cache site
