# The README's commands (run, test, docs). Each creates .venv (Python >= 3.12) and installs the project first.
# Python 3.12 (the DOLFINx wheel's version): python3.12 on PATH if it runs, else pyenv's 3.12.x.
PYTHON ?= $(shell if python3.12 -c '' 2>/dev/null; then echo python3.12; \
	  else ls -d $${PYENV_ROOT:-$$HOME/.pyenv}/versions/3.12.*/bin/python3.12 2>/dev/null | sort -V | tail -n 1; fi)
VENV := .venv
STAMP := $(VENV)/.installed

.PHONY: run test bench docs

$(STAMP): pyproject.toml
	@test -n "$(PYTHON)" || { echo "need Python >= 3.12 (python3.12 on PATH or under pyenv)"; exit 1; }
	$(PYTHON) -m venv $(VENV)
	$(VENV)/bin/python -m pip install -q -U pip
	$(VENV)/bin/python -m pip install -q -e '.[test,fe,nomad,dist,docs]'
	touch $(STAMP)

run: $(STAMP)
	$(VENV)/bin/python scripts/fit_patients.py --out out/fit

test: $(STAMP)
	$(VENV)/bin/python -m pytest -q -n 2 --dist loadscope

bench: $(STAMP)
	$(VENV)/bin/python scripts/bench_lo.py

# The documentation site, warnings as errors, the tutorial executed; open docs/_build/html/index.html.
docs: $(STAMP)
	$(VENV)/bin/python -m sphinx -W -E -q -b html docs docs/_build/html
