# SAIS Workbench — every target sets up .venv itself when it is missing or stale.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
PROFILE ?= quick
WORKERS ?= 2
# SCHEDULER=tcp://host:8786 runs the study tasks on a Dask cluster instead of local workers
SCHEDULER ?=
STUDY_EXEC = --workers $(WORKERS) $(if $(SCHEDULER),--scheduler $(SCHEDULER))
export OPENBLAS_NUM_THREADS ?= 1
export WORKBENCH_CACHE_DIR ?= $(CURDIR)/.cache/codegen

.PHONY: venv test study study-tracking-demo study-tracking study-navigation study-bound \
	study-alpha-rules bench lint clean-cache clean

venv: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

test: $(STAMP)
	$(PY) -m pytest

lint: $(STAMP)
	$(VENV)/bin/ruff check workbench studies tests benchmarks

study: study-tracking-demo study-tracking study-navigation study-bound

study-tracking-demo: $(STAMP)
	$(PY) -m studies.tracking_demo --profile $(PROFILE) --out reports/tracking_demo

study-tracking: $(STAMP)
	$(PY) -m studies.tracking_comparison --profile $(PROFILE) --out reports/tracking_comparison \
		$(STUDY_EXEC)

study-navigation: $(STAMP)
	$(PY) -m studies.navigation --profile $(PROFILE) --out reports/navigation $(STUDY_EXEC)

# Lemma 1 checked on SA-RMPPI episodes (issue 12): PROFILE=paper (35-60 min) or tiny; any other
# PROFILE (quick, the tracking study's full) runs the quick profile (about 2-2.5 min)
BOUND_PROFILE = $(if $(filter paper tiny,$(PROFILE)),$(PROFILE),quick)
study-bound: $(STAMP)
	$(PY) -m studies.free_energy_bound --profile $(BOUND_PROFILE) --out reports/free_energy_bound \
		$(STUDY_EXEC)

# SA-RMPPI activation per alpha rule (issue 8): 20 episodes per cell at variance 10 and 100
study-alpha-rules: $(STAMP)
	$(PY) -m studies.alpha_rules --episodes $(or $(EPISODES),20) --out reports/alpha_rules

bench: $(STAMP)
	$(PY) -m benchmarks --out reports/bench/bench.json

clean-cache:
	rm -rf .cache/codegen

clean:
	rm -rf $(VENV) .cache build *.egg-info
