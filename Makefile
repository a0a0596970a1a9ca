# pgnn-feedforward: every target works on a fresh clone (it installs what it needs first).
SHELL := /bin/bash
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
ROOT := $(abspath .)
MLFLOW_DB ?= sqlite:///$(ROOT)/mlruns/mlflow.db
export OMP_NUM_THREADS ?= 1

.PHONY: help install test test-full numba-signatures lint reproduce reproduce-check reproduce-spread reproduce-confirm ui server pg-uri-missing bench slurm-local clean

help:  ## list the targets
	@grep -E '^[a-z-]+:.*##' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  %-10s %s\n", $$1, $$2}'

install: $(VENV)/.installed  ## create .venv: CPU torch first, then the project with [dev]

# torch: the CPU build from PyTorch's CPU wheel index; where that index cannot be reached, the
# default index (a machine with a local CPU wheel gets that one). Then the project, with the
# versions CI tested (constraints.txt).
# The installer is uv (Astral's pip-compatible one, pinned in constraints.txt): it resolves, unpacks
# and compiles the bytecode on every core (measured: docs/performance.md). uv reads neither pip's
# configuration nor its PIP_* variables: scripts/uv_install.py hands them over (indexes, find-links
# where a machine keeps a local CPU torch wheel, constraints, certificates, proxy). Where uv cannot be
# installed or fails, the same steps run with pip (`make install UV_INSTALL=false` forces that path).
TORCH_CPU_INDEX ?= https://download.pytorch.org/whl/cpu
UV_INSTALL = $(PY) scripts/uv_install.py
PURELIB = "$$($(PY) -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')"

$(VENV)/.installed: pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	@echo "make install: uv (pip where uv fails), torch $(TORCH_CPU_INDEX) first"
	@( $(PY) -m pip install --quiet -c constraints.txt uv \
	  && { UV_HTTP_TIMEOUT=30 UV_HTTP_RETRIES=1 $(UV_INSTALL) torch==2.13.0 --index-url $(TORCH_CPU_INDEX) \
	         2> $(VENV)/torch-cpu-index.log \
	       || { echo "make install: $(TORCH_CPU_INDEX) failed ($$(tail -n 1 $(VENV)/torch-cpu-index.log | sed "s/^ *//");" \
	                 "all of it: $(VENV)/torch-cpu-index.log): torch from the default index"; \
	            $(UV_INSTALL) torch==2.13.0; }; } \
	  && $(UV_INSTALL) -c constraints.txt -e '.[dev]' ) \
	|| { echo "make install: uv failed (above); installing with pip"; \
	  { $(PY) -m pip install --quiet --no-compile torch==2.13.0 --index-url $(TORCH_CPU_INDEX) --retries 1 --timeout 30 \
	    || $(PY) -m pip install --quiet --no-compile torch==2.13.0; } \
	  && $(PY) -m pip install --quiet --no-compile -c constraints.txt -e '.[dev]' \
	  && { $(PY) -m compileall -q -j 0 $(PURELIB) > /dev/null || true; }; }
	@# the project's own bytecode on every core (pip's compilation is one file at a time; as pip, a file this
	@# Python cannot compile, torch's py312 test fixtures, is skipped)
	$(PY) -m compileall -q -j 0 pipeline stages > /dev/null || true
	@# and its numba kernels, for the signatures its tests and experiments use (pipeline/numba_warm.py): a first
	@# run then loads them instead of compiling (~1 min of a fresh `make test`); never fails the install
	$(PY) -m pipeline.numba_warm || echo "make install: the numba warm-up failed (above); kernels compile on first use"
	@$(PY) -c "import torch; print('installed torch', torch.__version__, '(CUDA build: large)' if torch.version.cuda else '(CPU build)')"
	touch $@

test: install  ## fast test suite, one worker per core (pytest-xdist; a file's tests stay on one worker)
	$(PY) -m pytest -q -n auto --dist loadfile

test-full: install  ## every test, including the slow ones (sweeps, whole experiments)
	$(PY) -m pytest -q -m ''

numba-signatures: install  ## after make test (and make reproduce): list the kernels' signatures make install compiles
	$(PY) -m pipeline.numba_warm --record

lint: install  ## ruff
	$(VENV)/bin/ruff check pipeline stages tests benchmarks

# every experiment of `make reproduce`, in order (conf/experiment/<name>.yaml; sweeps are set in
# the file with hydra.mode=MULTIRUN)
ALL_EXPERIMENTS := physics_arx physics_linear_motor physics_rot_trans physics_two_mass ilc_rot_trans \
  b1_arx_bias b1_linear_motor b1_noise_sweep k_two_mass b2_rot_trans b2_rot_trans_il b2_rot_trans_linear \
  emps_physics emps_narx emps
EXPERIMENTS ?= $(ALL_EXPERIMENTS)
# jobs of a sweep run at once (Hydra joblib launcher); empty = the machine's cores
JOBS ?=
# a subset rebuilds only its own report sections and keeps the rest of results/ (report.update)
REPORT_UPDATE := $(if $(filter-out $(ALL_EXPERIMENTS),$(EXPERIMENTS))$(filter-out $(EXPERIMENTS),$(ALL_EXPERIMENTS)),true,false)

reproduce: install  ## run every paper experiment, then write results/REPORT.md, summary.csv, figures
	$(PY) -m pipeline.reproduce $(if $(JOBS),--jobs $(JOBS)) $(EXPERIMENTS)
	$(PY) -m pipeline stages=[report] experiment_name=report run_name=report report.update=$(REPORT_UPDATE)

# is a result pinned down by its fit's tolerances? (issue 19; pipeline/perturbation.py)
#   CHECK=perturb: a second machine, emulated: every LM step's normal equations perturbed at relative
#                  PERTURB (another BLAS summation order); values must move by < 2 %
#   CHECK=tighten: every LM and SK tolerance divided by TIGHTEN, and the restarts' iteration caps
#                  times CAPS (a fit that stopped on its cap runs on); values must move by < 1 %
#   CHECK=isa:     every job under PIPELINE_ISA=$(ISA) (default native: each library's own code path, AVX-512
#                  on a server) against the default pinned AVX2 paths (issue 52); 0 values move on a CPU whose
#                  own paths are AVX2, and on this kind of CPU the opt-out's cost in bits shows
# Own cache and store under .perturbed/<CHECK>/ (the store emptied per run); compared key by key with results/summary.csv into
# results/check-<CHECK>.md and .csv
CHECK ?= perturb
PERTURB ?= 1e-13
TIGHTEN ?= 10
CAPS ?= 2
ISA ?= native
CHECK_ENV = $(if $(filter tighten,$(CHECK)),PIPELINE_TIGHTEN=$(TIGHTEN) PIPELINE_CAP_FACTOR=$(CAPS),$(if $(filter isa,$(CHECK)),PIPELINE_ISA=$(ISA),PIPELINE_PERTURB=$(PERTURB)))
CHECK_RTOL = $(if $(filter tighten,$(CHECK)),0.01,0.02)
CHECKED := $(ROOT)/.perturbed/$(CHECK)
reproduce-check: install  ## rerun every experiment perturbed (CHECK=perturb), tightened (CHECK=tighten) or on another code path (CHECK=isa), compare with results/
	@# a store of this run only (the cache stays: a rerun resumes), so its summary holds only EXPERIMENTS
	rm -rf $(CHECKED)/mlflow.db $(CHECKED)/mlflow.db.open.lock $(CHECKED)/artifacts $(CHECKED)/results/summary.csv
	$(CHECK_ENV) PIPELINE_CACHE=$(CHECKED)/cache MLFLOW_TRACKING_URI=sqlite:///$(CHECKED)/mlflow.db \
	  $(PY) -m pipeline.reproduce --results $(CHECKED)/results $(if $(JOBS),--jobs $(JOBS)) $(EXPERIMENTS)
	$(CHECK_ENV) PIPELINE_CACHE=$(CHECKED)/cache MLFLOW_TRACKING_URI=sqlite:///$(CHECKED)/mlflow.db \
	  $(PY) -m pipeline stages=[report] experiment_name=report run_name=report paths.results=$(CHECKED)/results
	$(PY) -m pipeline.perturbation results/summary.csv $(CHECKED)/results/summary.csv --out results \
	  --check $(CHECK) --rtol $(CHECK_RTOL) --setting "$(CHECK_ENV)"
	$(PY) -m pipeline stages=[report] experiment_name=report run_name=report report.update=$(REPORT_UPDATE)   # REPORT.md shows the check

# claim rows on a statistic over restarts (issue 52 item 2; pipeline/spread.py): the experiments whose network
# fits decide claim rows rerun with init_seed = each of SEEDS (the same data and evaluation noise, other initial
# weights and restarts), one store and results folder per init_seed under .spread/<SPREAD_CHECK or default>/;
# with the default run as init_seed 0, results/spread.csv gives each key's median and [min, max], and REPORT.md
# judges the claim rows on the median. SPREAD_CHECK=perturb|isa: the same init_seeds (0 included) under
# PIPELINE_PERTURB=$(PERTURB) or PIPELINE_ISA=$(ISA) in their own cache, their medians checked against
# results/spread.csv (results/spread-check-<SPREAD_CHECK>.md: passes when no claim row is separated from its spread
# and no decided verdict flips; keys that do not move with the restarts are stated to what results/check-tighten.csv
# moved them). Costs (SEEDS words) x the experiments' job time.
# Two runs at once need their own SPREAD_DIR=... (a second run on one folder is refused: it would empty the first's stores).
SEEDS ?= 1 2 3 4
SPREAD_EXPERIMENTS ?= b1_linear_motor k_two_mass b2_rot_trans
SPREAD_CHECK ?=
empty :=
space := $(empty) $(empty)
SPREAD_DIR := $(ROOT)/.spread/$(or $(SPREAD_CHECK),default)
SPREAD_ENV = $(if $(filter isa,$(SPREAD_CHECK)),PIPELINE_ISA=$(ISA),$(if $(filter perturb,$(SPREAD_CHECK)),PIPELINE_PERTURB=$(PERTURB)))
SPREAD_SEEDS = $(if $(SPREAD_CHECK),0 $(SEEDS),$(SEEDS))
SPREAD_LABELS = $(subst $(space),$(comma),$(strip $(if $(SPREAD_CHECK),,0) $(SPREAD_SEEDS)))
SPREAD_SUMMARIES = $(if $(SPREAD_CHECK),,results/summary.csv) $(foreach s,$(SPREAD_SEEDS),$(SPREAD_DIR)/seed$(s)/results/summary.csv)
reproduce-spread: install  ## rerun the fit-decided experiments with other init_seeds (SEEDS), judge claim rows on the median
	@$(if $(filter-out perturb isa,$(SPREAD_CHECK)),$(error SPREAD_CHECK=$(SPREAD_CHECK) is not known: leave it empty, or perturb, or isa))
	@test -n "$(SPREAD_CHECK)" -o -f results/summary.csv || { echo "make reproduce-spread: no results/summary.csv (init_seed 0): run make reproduce first"; exit 1; }
	@# one run per SPREAD_DIR at a time: a second one would empty the first one's per-seed stores under it
	@mkdir -p $(SPREAD_DIR); if command -v flock >/dev/null; then exec 9>$(SPREAD_DIR)/.lock; flock -n 9 || { \
	  echo "make reproduce-spread: another run is using $(SPREAD_DIR); wait for it, or give this one its own folder: SPREAD_DIR=$(SPREAD_DIR)-2"; exit 1; }; fi; \
	for s in $(SPREAD_SEEDS); do \
	  d=$(SPREAD_DIR)/seed$$s; echo "== init_seed $$s: $(SPREAD_EXPERIMENTS) ($(or $(SPREAD_ENV),default code path))"; \
	  rm -rf $$d/mlflow.db $$d/mlflow.db.open.lock $$d/artifacts $$d/results/summary.csv; \
	  $(SPREAD_ENV) $(if $(SPREAD_CHECK),PIPELINE_CACHE=$(SPREAD_DIR)/cache) MLFLOW_TRACKING_URI=sqlite:///$$d/mlflow.db \
	    $(PY) -m pipeline.reproduce --results $$d/results $(if $(JOBS),--jobs $(JOBS)) --override init_seed=$$s \
	    $(SPREAD_EXPERIMENTS) || exit 1; \
	  $(SPREAD_ENV) $(if $(SPREAD_CHECK),PIPELINE_CACHE=$(SPREAD_DIR)/cache) MLFLOW_TRACKING_URI=sqlite:///$$d/mlflow.db \
	    $(PY) -m pipeline stages=[report] experiment_name=report run_name=report paths.results=$$d/results || exit 1; \
	done
	$(PY) -m pipeline.spread build $(SPREAD_SUMMARIES) --labels $(SPREAD_LABELS) --setting "$(or $(SPREAD_ENV),default)" \
	  $(if $(SPREAD_CHECK),--out $(SPREAD_DIR) --name spread,--out results --keep results/spread.csv)
	$(if $(SPREAD_CHECK),$(SPREAD_CHECK_CMD) || true)
	@# report.update=true: the sections and rows of results/ stay as they are where this store has no runs of them; the
	@# header (the claim table, judged on the medians) is rebuilt
	$(PY) -m pipeline stages=[report] experiment_name=report run_name=report report.update=true

# the spread check against results/spread.csv; --confirm: every fresh-draw check of this setting (reproduce-confirm)
SPREAD_CHECK_CMD = $(PY) -m pipeline.spread check results/spread.csv $(SPREAD_DIR)/spread.csv --name $(SPREAD_CHECK) \
	  --setting "$(SPREAD_ENV)" --out results --keep results/spread-check-$(SPREAD_CHECK).csv \
	  $(if $(wildcard results/check-tighten.csv),--determination results/check-tighten.csv) \
	  $$(for f in $(ROOT)/.spread/confirm-$(SPREAD_CHECK)-*/spread-check-confirm.csv; do [ -f "$$f" ] && printf -- '--confirm %s ' "$$f"; done)
# a separated claim row confirmed, or not, by fresh draws of its own jobs (pipeline/spread.py, "--confirm"): the jobs
# of CONFIRM_JOB (an experiment and the row's overrides, e.g. 'experiment=b2_rot_trans model.hidden=[48]
# invert.gamma=1e-06') rerun with init_seed = each of CONFIRM_SEEDS (none of the spread's), once on the default
# paths and once under SPREAD_CHECK's setting, one store per side and seed under .spread/confirm-<check>-<hash>/
# (a rerun resumes from their caches); the two fresh spreads are checked against each other, then
# results/spread-check-<check> is judged again with every such check. Costs 2 x (CONFIRM_SEEDS words) x the jobs' time.
CONFIRM_SEEDS ?= 5 6 7 8 9
CONFIRM_JOB ?=
CONFIRM_DIR = $(ROOT)/.spread/confirm-$(SPREAD_CHECK)-$(shell printf '%s' '$(CONFIRM_JOB)' | sha256sum | cut -c1-8)
CONFIRM_RUNS = $(foreach s,$(CONFIRM_SEEDS),$(CONFIRM_DIR)/default-seed$(s)/results/summary.csv \
	$(CONFIRM_DIR)/$(SPREAD_CHECK)-seed$(s)/results/summary.csv)
reproduce-confirm: install  ## fresh draws of a separated claim row's jobs (CONFIRM_JOB) on both sides of a spread check
	@$(if $(filter perturb isa,$(SPREAD_CHECK)),,$(error SPREAD_CHECK=$(SPREAD_CHECK): give the check to confirm, perturb or isa))
	@$(if $(word 2,$(CONFIRM_SEEDS)),,$(error CONFIRM_SEEDS="$(CONFIRM_SEEDS)": a spread needs at least two init_seeds (default 5 6 7 8 9)))
	@$(if $(strip $(CONFIRM_JOB)),,$(error CONFIRM_JOB is empty: give the separated row's job, e.g. CONFIRM_JOB='experiment=b2_rot_trans model.hidden=[48] invert.gamma=1e-06'))
	@test -f results/spread.csv -a -f $(SPREAD_DIR)/spread.csv || { echo "make reproduce-confirm: no spread check to \
	confirm (results/spread.csv, $(SPREAD_DIR)/spread.csv): run make reproduce-spread SPREAD_CHECK=$(SPREAD_CHECK) first"; exit 1; }
	@mkdir -p $(CONFIRM_DIR); printf '%s\n' '$(CONFIRM_JOB)' > $(CONFIRM_DIR)/job.txt
	$(MAKE) --no-print-directory -j $(or $(JOBS),$(shell nproc)) $(CONFIRM_RUNS)
	$(PY) -m pipeline.spread build $(foreach s,$(CONFIRM_SEEDS),$(CONFIRM_DIR)/default-seed$(s)/results/summary.csv) \
	  --labels $(subst $(space),$(comma),$(strip $(CONFIRM_SEEDS))) --setting default --out $(CONFIRM_DIR) --name spread-default
	$(PY) -m pipeline.spread build $(foreach s,$(CONFIRM_SEEDS),$(CONFIRM_DIR)/$(SPREAD_CHECK)-seed$(s)/results/summary.csv) \
	  --labels $(subst $(space),$(comma),$(strip $(CONFIRM_SEEDS))) --setting "$(SPREAD_ENV)" --out $(CONFIRM_DIR) --name spread-other
	$(PY) -m pipeline.spread check $(CONFIRM_DIR)/spread-default.csv $(CONFIRM_DIR)/spread-other.csv --name confirm \
	  --setting "$(SPREAD_ENV)" --out $(CONFIRM_DIR) || true
	$(SPREAD_CHECK_CMD) || true
	$(PY) -m pipeline stages=[report] experiment_name=report run_name=report report.update=true
# one side and init_seed of reproduce-confirm: the job(s) in a store of their own, then its report (summary.csv)
$(ROOT)/.spread/confirm-%/results/summary.csv:
	@set -f; d=$(ROOT)/.spread/confirm-$*; run=$${d##*/}; seed=$${run##*-seed}; side=$${run%-seed*}; \
	env=$$( [ "$$side" = default ] || echo "$(SPREAD_ENV)" ); \
	echo "== $(CONFIRM_JOB) init_seed=$$seed ($${env:-default code path})"; \
	rm -rf $$d/mlflow.db $$d/mlflow.db.open.lock $$d/artifacts; mkdir -p $$d; \
	env $$env PIPELINE_CACHE=$${d%/*}/cache-$$side MLFLOW_TRACKING_URI=sqlite:///$$d/mlflow.db \
	  $(PY) -m pipeline $(CONFIRM_JOB) hydra.mode=RUN init_seed=$$seed > $$d.log 2>&1 \
	  || { echo "make reproduce-confirm: the job failed, its output: $$d.log"; tail -n 5 $$d.log; exit 1; }; \
	env $$env PIPELINE_CACHE=$${d%/*}/cache-$$side MLFLOW_TRACKING_URI=sqlite:///$$d/mlflow.db \
	  $(PY) -m pipeline stages=[report] experiment_name=report run_name=report paths.results=$$d/results >> $$d.log 2>&1
ui: install  ## MLflow UI on http://127.0.0.1:5000 over the same store as the runs
	@echo "The project's experiments (open a link for its runs table):"
	@$(PY) -c "from pipeline.tracking import experiment_links; print('\n'.join(experiment_links()) or '  none yet: run make reproduce')"
	$(VENV)/bin/mlflow server --backend-store-uri "$${MLFLOW_TRACKING_URI:-$(MLFLOW_DB)}" \
	  --artifacts-destination "$(ROOT)/mlruns/artifacts" --host 127.0.0.1 --port 5000 --workers 1

# the team tracking server (README, "Parallel sweeps"): MLflow on PostgreSQL, artifacts proxied into
# ARTIFACTS. psycopg is the optional extra [postgres], installed here if missing. Jobs and `make ui`
# elsewhere use MLFLOW_TRACKING_URI=http://<host>:$(PORT). Nodes that reach the server by a name (not
# localhost or a private IP) need ALLOWED_HOSTS=<name>:$(PORT) (MLflow's DNS-rebinding guard).
# ARTIFACTS, HOST, PORT, ALLOWED_HOSTS: on the command line (the environment's HOST is not taken);
# PG_URI from the command line or the environment (its password: ~/.pgpass or PGPASSWORD, not the URI).
PG_URI ?=
ARTIFACTS = $(ROOT)/mlruns/server-artifacts
HOST = 127.0.0.1
PORT = 5000
ALLOWED_HOSTS =
comma := ,
server: $(if $(PG_URI),install,pg-uri-missing)  ## team MLflow server on PostgreSQL (PG_URI=postgresql+psycopg://... required)
	@$(PY) -c 'import psycopg' 2>/dev/null || $(PY) -m pip install --quiet -c constraints.txt -e '.[postgres]'
	@echo "MLflow server on PostgreSQL: http://$(HOST):$(PORT), artifacts in $(ARTIFACTS)"
	@$(VENV)/bin/mlflow server --backend-store-uri "$(PG_URI)" --artifacts-destination "$(ARTIFACTS)" \
	  --host $(HOST) --port $(PORT) $(if $(ALLOWED_HOSTS),--allowed-hosts "$(ALLOWED_HOSTS)$(comma)localhost:*$(comma)127.0.0.1:*")

pg-uri-missing:
	$(error PG_URI is missing: make server PG_URI=postgresql+psycopg://USER@DBHOST:5432/mlflow ARTIFACTS=/srv/mlflow-artifacts HOST=0.0.0.0)

bench: install  ## print wall times (stages per plant, ILC trials, solvers)
	@for b in benchmarks/bench_*.py; do echo "== $$b"; $(PY) $$b || exit 1; done

# a one-node SLURM on this machine for hydra/launcher=slurm and tests/test_slurm.py (Debian, root, no
# systemd needed): installs slurm-wlm, munge, slurmdbd and MariaDB if missing, starts them, waits until
# the node is idle; rerunning is fine. SLURM_LOCAL=stop stops every daemon, SLURM_LOCAL=status lists them
SLURM_LOCAL ?= start
slurm-local:  ## one-node SLURM on this machine, partition debug (as root; SLURM_LOCAL=stop stops it)
	bash scripts/slurm-local.sh $(SLURM_LOCAL)

clean:  ## remove caches and stores (keeps results/)
	rm -rf .cache .perturbed outputs multirun mlruns .pytest_cache
	find pipeline -path "*/__pycache__/numba-*" -prune -exec rm -rf {} +
