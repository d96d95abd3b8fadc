# Two commands on a fresh Debian 12 machine (as root): `make demo` and `make test`.
SHELL := /bin/bash
VENV := .venv
PY := $(VENV)/bin/python
DEB_PKGS := python3-dolfinx-real python3-gmsh python3-meshio python3-mpi4py python3-petsc4py \
            libopenblas0-pthread mpi-default-bin python3-venv python3-matplotlib python3-scipy \
            python3-pygalmesh python3-skimage invesalius-examples \
            python3-fastapi python3-uvicorn chromium chromium-driver python3-selenium \
            paraview python3-paraview xvfb libcgal-dev libeigen3-dev
export OMP_NUM_THREADS ?= 1
export OPENBLAS_NUM_THREADS ?= 1

.PHONY: demo explore test test-pypi check install bench lint clean

WEB := scripts/web

install: $(VENV)/.installed $(WEB)/node_modules/.installed

# Debian packages: installed only when one is missing (dpkg-query), never twice.
.deb-installed: Makefile
	@missing=$$(for p in $(DEB_PKGS); do dpkg-query -W -f='$${Status}\n' $$p 2>/dev/null \
	  | grep -q 'install ok installed' || echo $$p; done); \
	if [ -n "$$missing" ]; then echo "apt-get install $$missing"; \
	  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing; fi
	@/usr/bin/python3 -c "import dolfinx, gmsh, meshio, pygalmesh, skimage, fastapi, uvicorn, selenium" \
	  && touch $@

# PyPI packages (SimpleITK) are installed against a constraints file that pins Debian's numpy
# and scipy, so pip can never replace the numpy dolfinx was built with.
$(VENV)/.installed: .deb-installed pyproject.toml
	@test -x $(PY) || /usr/bin/python3 -m venv --system-site-packages $(VENV)
	@/usr/bin/python3 -c "import numpy, scipy; print(f'numpy=={numpy.__version__}\nscipy=={scipy.__version__}')" > $(VENV)/constraints.txt
	$(PY) -m pip install -q -c $(VENV)/constraints.txt -e '.[test,ct]'
	@touch $@

# The explorer page's three.js, from the npm registry at the version of the lock file
# (Debian's npm where the machine has none).
$(WEB)/node_modules/.installed: $(WEB)/package.json $(WEB)/package-lock.json .deb-installed
	@command -v npm >/dev/null || (apt-get update -qq && \
	  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq npm)
	cd $(WEB) && npm ci --no-audit --no-fund --loglevel=error
	@touch $@

demo: install
	$(PY) scripts/demo.py

# The browser explorer on the demo's real face (planned first if out/demo has none);
# the synthetic one: `make explore PLAN=out/demo/class3-asym/report.json`.
PLAN ?= out/demo/cranium/report.json
explore: install
	@test -f $(PLAN) || $(PY) scripts/demo.py
	$(PY) scripts/explore_web.py --plan-report $(PLAN)

# Every tier (tests/conftest.py): unit, integration on the tiny heads, scripts, browser,
# clients (ParaView); a pytest-xdist worker per core, each test module on one worker (its
# fixtures built once). On Debian's dolfinx, then on PyPI's (test-pypi, below).
test: install
	$(PY) -m ruff check .
	$(PY) -m pytest -q -n auto --dist loadfile --durations=25
	@$(MAKE) --no-print-directory test-pypi

# The unit tier alone (each part on a cube or a block, no head: under a minute).
check: install
	$(PY) -m ruff check .
	$(PY) -m pytest -q -m unit

# The second target (README: the pip route): the same suite on PyPI's current FEniCSx
# (dolfinx 0.11, MPICH) in its own venv, from a Python 3.12 or later (scripts/python312.sh);
# skipped in one line where the machine has none. pygalmesh has no wheel: pip builds it
# against Debian's CGAL and Eigen; where it cannot, that target's CT tests skip with the reason.
PYPI_VENV := .venv-pypi
PYPI_PY := $(PYPI_VENV)/bin/python

$(PYPI_VENV)/.installed: .deb-installed pyproject.toml
	@test -x $(PYPI_PY) || $$(scripts/python312.sh) -m venv $(PYPI_VENV)
	$(PYPI_PY) -m pip install -q -e '.[fenicsx,test,ct]'
	@$(PYPI_PY) -m pip install -q pygalmesh || echo "pygalmesh could not be built: the CT tests of the PyPI target skip"
	@touch $@

test-pypi:
	@if [ -z "$$(scripts/python312.sh)" ]; then \
	  echo "skipped the PyPI target (dolfinx 0.11): no Python 3.12 or later on the PATH or in pyenv"; \
	else $(MAKE) --no-print-directory $(PYPI_VENV)/.installed $(WEB)/node_modules/.installed && \
	  $(PYPI_PY) -m pytest -q -n auto --dist loadfile --durations=10; fi

bench: install
	$(PY) scripts/bench.py forward
	$(PY) scripts/bench.py plan

clean:
	rm -rf $(VENV) $(PYPI_VENV) .deb-installed out
