# SAIS Workbench — every target sets up .venv itself when it is missing or stale.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
WB     := $(VENV)/bin/workbench
STAMP  := $(VENV)/.installed
PROFILE ?= quick
WORKERS ?= 2
# SCHEDULER=tcp://host:8786 runs the study tasks on a Dask cluster instead of local workers
SCHEDULER ?=
STUDY_EXEC = --workers $(WORKERS) $(if $(SCHEDULER),--scheduler $(SCHEDULER))
export OPENBLAS_NUM_THREADS ?= 1
export WORKBENCH_CACHE_DIR ?= $(CURDIR)/.cache/codegen

.PHONY: venv test typecheck study study-tracking-demo study-tracking study-navigation study-bound \
	study-sampling-safety study-arena tune-arena reports docs bench lint clean-cache clean

venv: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

# the type check ([tool.mypy] in pyproject.toml) first, then the test suite
test: typecheck
	$(PY) -m pytest

typecheck: $(STAMP)
	$(VENV)/bin/mypy

lint: $(STAMP)
	$(VENV)/bin/ruff check workbench studies tests benchmarks examples

# every study target is `workbench run NAME --profile $(PROFILE) --out DIR`; SET='key=value ...'
# adds --set overrides (e.g. make study-tracking SET='noise_std=5 n_seeds=4')
SETS = $(foreach s,$(SET),--set $(s))

# Each run has its own folder, so that the targets run one after another (a folder holds one
# config's run): the quick profile's in reports/<study folder>, another profile's in
# reports/<study folder>_<profile>, a run with SET in reports/<study folder>_<profile>_set-<a
# checksum of SET>; OUT=DIR chooses the folder (a rerun into it continues the stored run)
OUT ?=
quote = '$(subst ','\'',$(1))'
SET_TAG = $(if $(SET),_set-$(firstword $(shell printf '%s' $(call quote,$(SET)) | cksum)))
run_dir = $(if $(OUT),$(OUT),reports/$(1)$(if $(or $(SET),$(filter-out quick,$(2))),_$(2))$(SET_TAG))
run_out = --out $(call quote,$(call run_dir,$(1),$(2)))

study: study-tracking-demo study-tracking study-navigation study-bound study-sampling-safety \
	study-arena reports

study-tracking-demo: $(STAMP)
	$(WB) run tracking-demo --profile $(PROFILE) $(SETS) $(call run_out,tracking_demo,$(PROFILE))

study-tracking: $(STAMP)
	$(WB) run tracking --profile $(PROFILE) $(STUDY_EXEC) $(SETS) \
		$(call run_out,tracking_comparison,$(PROFILE))

# navigation and bound have tiny/quick/paper profiles; any other PROFILE (the tracking study's
# full) runs their quick profile
NAV_PROFILE = $(if $(filter paper tiny,$(PROFILE)),$(PROFILE),quick)
study-navigation: $(STAMP)
	$(WB) run navigation --profile $(NAV_PROFILE) $(STUDY_EXEC) $(SETS) \
		$(call run_out,navigation,$(NAV_PROFILE))

# Lemma 1 checked on SA-RMPPI episodes: quick about 2-2.5 min, paper 35-60 min
study-bound: $(STAMP)
	$(WB) run free-energy-bound --profile $(NAV_PROFILE) $(STUDY_EXEC) $(SETS) \
		$(call run_out,free_energy_bound,$(NAV_PROFILE))

# every safe-sampling method on one sampler (claim 1 of the paper): tiny/quick/paper profiles
study-sampling-safety: $(STAMP)
	$(WB) run sampling-safety --profile $(NAV_PROFILE) $(STUDY_EXEC) $(SETS) \
		$(call run_out,sampling_safety,$(NAV_PROFILE))

# the arena: controllers x systems x generated maps x disturbances, declared comparisons decided
# group-sequentially (quick: a few minutes; PROFILE=verdict: claim (i) on the double integrator
# at velocity variance 50 and 100, hand and tuned, at most an hour; PROFILE=decide or paper:
# for a cluster, SCHEDULER=tcp://host:8786)
ARENA_PROFILE = $(if $(filter tiny verdict decide paper,$(PROFILE)),$(PROFILE),quick)
study-arena: $(STAMP)
	$(WB) run arena --profile $(ARENA_PROFILE) $(STUDY_EXEC) $(SETS) \
		$(call run_out,arena,$(ARENA_PROFILE))

# equal-budget tuning of the arena's controllers; ships the result as their tuned defaults
# (workbench/scenarios/tuned.json)
TUNE_PROFILE = $(if $(filter tiny verdict,$(PROFILE)),$(PROFILE),quick)
tune-arena: $(STAMP)
	$(WB) run arena-tuning --profile $(TUNE_PROFILE) $(STUDY_EXEC) $(SETS) \
		$(call run_out,arena_tuning,$(TUNE_PROFILE))
	$(PY) -m studies.arena.tuning $(call quote,$(call run_dir,arena_tuning,$(TUNE_PROFILE)))
	@echo "tuned values shipped; if they changed, an arena folder run with the old ones is refused" \
		"(naming the differences): make study-arena OUT=DIR, or delete that folder"

# reports/index.html: every study's report (each profile's run), figures, tables and manifest,
# offline
reports: $(STAMP)
	$(WB) report

# the documentation site (guides, executed tutorials, the API from the docstrings) into
# reports/docs/, offline; warnings are errors (tests/test_docs_site.py builds it too)
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict

# benchmarks live outside the library: python -m benchmarks [--out FILE] [--repeats N]
bench: $(STAMP)
	$(PY) -m benchmarks

clean-cache:
	rm -rf .cache/codegen

clean:
	rm -rf $(VENV) .cache .mypy_cache build *.egg-info
