# The two README commands: `make demo` and `make test`. Only Python 3.11 (and make) are needed.
PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: setup demo test bench prior clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $(STAMP)

setup: $(STAMP)

demo: $(STAMP)
	$(BIN)/f2l demo --out demo_out

test: $(STAMP)
	$(BIN)/python -m pytest -q

bench: $(STAMP)
	$(BIN)/f2l bench --faces 1

# Rebuild the shipped Sun+Sky GMM prior from the project's own sky corpus (~15 min on 2 cores).
prior: $(STAMP)
	$(BIN)/f2l sky-corpus --out build/sky_corpus --n 200 --seed 0 --json
	$(BIN)/f2l build-prior build/sky_corpus --model sunsky --components 6 --seed 0 \
		--out plugins/f2l_builtin_models/data/sunsky_prior.json --json

clean:
	rm -rf $(VENV) demo_out
