"""The GA3CE training loop (the paper's recipe, docs/paper.md; every knob is a `TrainConfig` field).

AdamW with a per-step schedule (linear warm-up, then cosine decay to 0), gradient clipping, the
arccos loss and view-noise augmentation. Seeded and deterministic on CPU: the batches, the
augmentation and the dropout of epoch e are drawn from (seed, e), so a resumed run matches an
uninterrupted one.

A run folder holds: config.json, last.pt (written atomically after every epoch, with the optimiser,
for --resume), best.pt (lowest validation 3D MAE), history.csv and curves.png (loss and val MAE per
epoch); a pointer model whose g0 is frozen (ModelConfig.pointer_g0) also holds g0/, the run of the
no-objects model it starts from (trained first with the same recipe and seed). Python API:
`train(TrainConfig(store=..., out=...)) -> run folder`. Under torchrun the
same call trains data-parallel (distributed.py): the global batch stays `batch_size` frames.
"""
from __future__ import annotations

import contextlib
import csv
import json
import logging
import math
import os
import shutil
import time
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from tqdm import tqdm

from ..errors import ConfigError
from ..model import GA3CE, ModelConfig, angular_loss
from ..store import ContextStore, open_store
from .augment import object_dropout, object_jitter, view_noise
from .checkpoint import CheckpointError, check_checkpoint, load_checkpoint, save_checkpoint
from .dataset import BATCHINGS, Batch, BucketBatchSampler, ContextDataset, store_fingerprint
from .distributed import Ranks
from .evaluate import predict
from .plots import plot_curves
from .profiles import DatasetProfile
from .schedule import warmup_cosine_lr

log = logging.getLogger("ga3ce_prep.train")


@dataclass
class TrainConfig:
    """Everything a training run depends on (saved as config.json and in every checkpoint)."""

    store: str = ""  # the 3D context store to train on (from `ga3ce-prep run`)
    out: str = "runs/ga3ce"  # the run folder
    epochs: int = 20  # training epochs (the paper's 20)
    batch_size: int | None = (
        # frames per batch; unset: the paper's for the store's dataset
        # (DatasetProfile.batch_size: 32 on GFIE and CAD-120, 64 on GAFA, else 32)
        None)
    lr: float = 3e-4  # peak AdamW learning rate, below the paper's: docs/training.md "Learning rate"
    weight_decay: float = 0.1  # AdamW weight decay (the paper's)
    warmup_epochs: float = 4.0  # linear warm-up over this many epochs (stepped per batch), then cosine decay to 0
    grad_clip: float = 0.1  # clip the gradient's global L2 norm to this (the paper's)
    view_noise: Literal["auto", "on", "off"] = (
        # augment v <- normalise(v + eps): on, off, or auto = as the paper on this dataset (DatasetProfile: on for GFIE)
        "auto")
    view_noise_amplitude: float = 0.5  # amplitude a of eps ~ U[-a, a]^3 (0.5: about 22 degrees on average)
    object_dropout: float = (
        # probability of dropping each object token of a training frame (ours,
        # 0 = the paper's recipe): docs/studies/2026-11-29-what-the-objects-add.md
        0.0)
    object_frame_dropout: float = (
        # probability of hiding all objects of a training frame (ours, 0
        # = the paper's recipe): the model also learns to do without them
        0.0)
    first_pass_loss: float = (
        # weight of the arccos loss of the pointer model's first pass g0
        # (ours; g has weight 1): g0 is trained as the no-objects model it is
        1.0)
    object_jitter: float = (
        # std of Gaussian noise added to each object position in training, metres (ours, 0 = the paper's recipe)
        0.0)
    seed: int = 0  # seed of every random draw (same seed, same weights on CPU)
    device: Literal["cpu", "cuda"] = "cpu"  # where to train
    threads: int = 2  # CPU threads of torch (keep at the number of free cores)
    n_max: int | None = (
        # object slots per frame: None pads to the batch's largest count; N pads to N, keeping the largest masks
        None)
    batching: Literal["mixed", "sorted", "shuffled"] = (
        # how frames are grouped into batches, the same for every arm of a comparison: shuffled =
        # at random (rooms mixed; cheap with micro_batches), mixed = by object count in 4 groups
        # (little padding, many rooms a batch), sorted = by count (least padding, a room or two a
        # batch): docs/training.md "Batches"
        "shuffled")
    micro_batches: int = (
        # run each batch as this many parts of similar object count, each padded to its own largest
        # count, their gradients summed into one optimiser step: the same step with less padding
        # (what makes `shuffled` batches cheap; 1 = the whole batch at once; arms that read no
        # objects always run whole batches)
        4)
    train_frames: int | None = None  # train on an evenly spaced subset of this many frames (short runs); unset = all
    val_frames: int | None = None  # validate on an evenly spaced subset of this many frames; unset = all
    progress: bool = True  # progress bars (else one log line per epoch)
    model: ModelConfig = field(default_factory=ModelConfig)  # architecture and ablation switches

    def __post_init__(self) -> None:
        if isinstance(self.model, dict):
            self.model = ModelConfig.from_dict(self.model)
        if self.view_noise not in ("auto", "on", "off"):
            raise ConfigError(f"view_noise must be auto, on or off, got {self.view_noise!r}")
        if self.epochs < 1 or (self.batch_size is not None and self.batch_size < 1):
            raise ConfigError(f"epochs ({self.epochs}) and batch_size ({self.batch_size}) must be >= 1")
        if not (0.0 <= self.object_dropout < 1.0 and 0.0 <= self.object_frame_dropout < 1.0) or self.object_jitter < 0:
            raise ConfigError(f"object_dropout and object_frame_dropout must be in [0, 1) and object_jitter >= 0, got "
                              f"{self.object_dropout}, {self.object_frame_dropout} and {self.object_jitter}")
        if self.micro_batches < 1:
            raise ConfigError(f"micro_batches must be >= 1, got {self.micro_batches}")
        if self.batching not in BATCHINGS:
            raise ConfigError(f"batching must be one of {', '.join(BATCHINGS)}, got {self.batching!r}")
        if self.device not in ("cpu", "cuda"):
            raise ConfigError(f"device must be cpu or cuda, got {self.device!r}")

    def to_dict(self) -> dict[str, Any]:
        d = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "model"}
        d["model"] = self.model.to_dict()
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TrainConfig:
        known = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in known})

    def uses_view_noise(self, profile: DatasetProfile) -> bool:
        """Whether to augment v when training on a store of the dataset `profile`."""
        return self.view_noise == "on" or (self.view_noise == "auto" and profile.view_noise)


def setup_torch(threads: int, device: str, index: int | None = None) -> torch.device:
    """Thread count, deterministic algorithms, and the device (refusing cuda when absent); index:
    the GPU of this process (data-parallel training)."""
    torch.set_num_threads(threads)
    if device == "cuda":
        if not torch.cuda.is_available():
            raise ConfigError("--device cuda: this torch build sees no CUDA device (use --device cpu)")
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
        torch.use_deterministic_algorithms(True, warn_only=True)
    else:
        torch.use_deterministic_algorithms(True)
    return torch.device(device, index) if device == "cuda" and index is not None else torch.device(device)


def _epoch_seed(seed: int, epoch: int, stream: int, rank: int = 0) -> int:
    return int(np.random.SeedSequence([seed, epoch, stream, *([rank] if rank else [])]).generate_state(1)[0])


def _write_history(history: list[dict[str, Any]], out: Path) -> None:
    if not history:
        return
    with open(out / "history.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(history[0]))
        w.writeheader()
        w.writerows(history)
    plot_curves(history, out / "curves.png")


def _mean_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Mean angle in degrees between the unit vectors a and b (n, 3). (Not geometry.angular_error_deg:
    that one re-normalises, which moves the last bits of the recorded validation figures.)"""
    return float(np.degrees(np.arccos(np.clip(np.sum(a * b, axis=1), -1, 1))).mean())


def run_done(run: Path, epochs: int) -> bool:
    """Whether the run folder holds a finished run of `epochs` epochs (best.pt and the last epoch in
    history.csv)."""
    hist = run / "history.csv"
    if not (run / "best.pt").exists() or not hist.exists():
        return False
    with open(hist) as f:
        rows = list(csv.DictReader(f))
    return bool(rows) and int(rows[-1]["epoch"]) + 1 >= epochs


def ensure_trained(config: TrainConfig, force: bool = False, resume: bool = True, twin: Path | None = None) -> Path:
    """The run of `config` in config.out, trained unless it is done; returns its best.pt.

    Done means: the run finished config.epochs epochs, and its checkpoint was trained on this
    store (fingerprint) with this configuration, up to the fields that cannot change a result
    (`checkpoint.RESULT_NEUTRAL`); a finished run of another store or configuration is refused
    (CheckpointError naming the differences), never silently reused. An unfinished run is resumed
    (`resume`; train refuses a changed one). force: train again over whatever is there. twin: for a
    frozen-g0 design, a finished run of its no-objects twin (same store, recipe and seed), copied in
    as its g0 stage instead of training that again (`reuse_g0`)."""
    run = Path(config.out)
    if twin is not None and config.model.g0_frozen and not force:
        reuse_g0(run, twin, config.epochs)
    if not force and run_done(run, config.epochs):
        check_checkpoint(load_checkpoint(run / "best.pt"), run / "best.pt",
                         store_fingerprint(open_store(config.store)), config.to_dict())
        return run / "best.pt"
    log.info("training into %s", run)
    train(config, resume=resume and (run / "last.pt").exists() and not force, force=force)
    return run / "best.pt"


def g0_run(config: TrainConfig, resume: bool = False, force: bool = False) -> Path:
    """The no-objects model a frozen-g0 pointer model starts from, with config's recipe and seed in
    config.out/g0: reused when finished, else resumed or trained (train's resume and force mean
    the same for it as for the run); returns its best.pt."""
    run = Path(config.out) / "g0"
    g0 = replace(config, out=str(run), model=replace(config.model, use_objects=False))
    overwrite = force and not resume
    if overwrite or not run_done(run, config.epochs):
        log.info("training g0, the model without objects, into %s", run)
        train(g0, resume=(run / "last.pt").exists() and not overwrite, force=force)
    return run / "best.pt"


def reuse_g0(run: Path, twin: Path, epochs: int) -> bool:
    """Give a frozen-g0 run its g0 stage from `twin`, a finished run of its no-objects twin (same
    store, recipe and seed: the same weights, tests/test_train.py), when it has none yet; whether
    it did."""
    g0 = Path(run) / "g0"
    if g0.exists() or not run_done(Path(twin), epochs):
        return False
    shutil.copytree(twin, g0)
    return True


def _splits(config: TrainConfig, store: ContextStore) -> tuple[ContextDataset, ContextDataset | None]:
    """The training frames and the validation frames (None when the store has none)."""
    train_ds = ContextDataset(store, "train", max_frames=config.train_frames)
    if len(train_ds) == 0:
        raise ConfigError(f"{config.store}: no training frames with a view prior and ground-truth gaze "
                          f"(splits: {store.split_names}); build the store from a dataset with a train split")
    val_ds = ContextDataset(store, "val", max_frames=config.val_frames) if "val" in store.split_names else None
    if val_ds is None or len(val_ds) == 0:
        log.warning("%s has no validation frames: best.pt will be the last epoch", config.store)
        return train_ds, None
    return train_ds, val_ds


def _appearance_only(out: Path, state: dict[str, Any], model: GA3CE, epochs: int, prior: float) -> Path:
    """The "appearance only" run (use_context off): g = v has nothing to train, so last.pt and
    best.pt hold the parameter-free model at the last epoch with the v prior's validation MAE, for
    evaluate and ablate to read like any other run."""
    history = [{"epoch": epochs - 1, "step": 0, "lr": 0.0, "train_loss": float("nan"), "train_mae": float("nan"),
                "val_mae": prior, "val_prior_mae": prior, "seconds": 0.0, "samples_per_s": float("nan")}]
    ckpt = {**state, "epoch": epochs - 1, "model": model.state_dict(), "history": history, "best_val": prior}
    save_checkpoint(out / "last.pt", ckpt)
    save_checkpoint(out / "best.pt", ckpt)
    _write_history(history, out)
    log.info("appearance only (use_context off): g = v, nothing to train")
    return out


def augment_objects(b: Batch, generator: torch.Generator, dropout: float, frame_dropout: float,
                    jitter: float) -> Batch:
    """b with each real object dropped with probability `dropout`, all objects of a frame with
    probability `frame_dropout`, and each position moved by N(0, jitter^2) metres per coordinate
    (training only); b itself, no draw, when all are 0."""
    if dropout > 0 or frame_dropout > 0:
        b = replace(b, mask=object_dropout(b.mask, generator, dropout, frame_dropout))
    if jitter > 0:
        b = replace(b, objects=object_jitter(b.objects, generator, jitter))
    return b


def train_step(model: torch.nn.Module, optimizer: torch.optim.Optimizer, b: Batch, view: torch.Tensor, lr: float,
               grad_clip: float, weight: float = 1.0, first_pass_loss: float = 1.0, parts: int = 1) -> torch.Tensor:
    """One optimiser step on batch b with view prior `view` (B, 3) (augmented or not): forward,
    arccos loss, backward, gradient clipping at L2 norm grad_clip, AdamW at learning rate lr.
    weight scales the loss for the backward pass (data-parallel: this rank's share of the global
    batch times the world size); the pointer model's first pass g0 adds its arccos loss times
    first_pass_loss. parts > 1 runs the batch as that many parts of similar object count
    (`Batch.split_by_count`), each loss weighted by its share of the frames, gradients summed:
    the same step up to rounding. Returns the batch's mean loss of g (radians, detached, unscaled)."""
    optimizer.zero_grad(set_to_none=True)
    pieces = b.split_by_count(parts) if parts > 1 else [(b, None)]
    mean_loss = torch.zeros((), device=view.device)
    no_sync = getattr(model, "no_sync", None)   # data-parallel: all-reduce once, after the last part
    for i, (p, rows) in enumerate(pieces):
        share = len(p) / len(b)
        with contextlib.nullcontext() if i == len(pieces) - 1 or no_sync is None else no_sync():
            *firsts, g = model(view if rows is None else view[rows], p.pose, p.head_pos, p.objects, p.mask,
                               all_passes=True)
            loss = angular_loss(g, p.gaze)
            total = loss
            for g0 in firsts:
                total = total + first_pass_loss * angular_loss(g0, p.gaze)
            (total * (weight * share)).backward()
        mean_loss = mean_loss + loss.detach() * share
    torch.nn.utils.clip_grad_norm_([p for group in optimizer.param_groups for p in group["params"]], grad_clip)
    for group in optimizer.param_groups:
        group["lr"] = lr
    optimizer.step()
    return mean_loss


def train(config: TrainConfig, resume: bool = False, force: bool = False,
          stop_after_epochs: int | None = None) -> Path:
    """Train GA3CE on config.store into the run folder config.out; returns the run folder.

    resume: continue from out/last.pt (refused if the store or the configuration changed, unless
    force). force without resume: overwrite an existing run. An existing run is otherwise refused.
    stop_after_epochs: return after this many epochs of this call (a time-boxed job); the run is
    then continued with resume=True and ends identical to an uninterrupted one.
    Under torchrun every process calls it (distributed.py); rank 0 writes the run folder.
    """
    ranks = Ranks.from_env()
    device = setup_torch(config.threads, config.device, ranks.local if ranks.world > 1 else None)
    joined = ranks.join(device)
    try:
        return _train(config, ranks, device, resume, force, stop_after_epochs)
    finally:
        if joined:
            ranks.leave()


def _train(config: TrainConfig, ranks: Ranks, device: torch.device, resume: bool, force: bool,
           stop_after_epochs: int | None) -> Path:
    out = Path(config.out)
    last_path, best_path = out / "last.pt", out / "best.pt"
    if last_path.exists() and not resume and not force:
        raise CheckpointError(f"{out} already holds a run (last.pt): pass --resume to continue it, "
                              "--force to overwrite it, or choose another --out")
    # the data (a damaged store is refused before the run folder exists), and the configuration as
    # the run folder records it
    store = open_store(config.store, verify=True)
    if ranks.main:
        out.mkdir(parents=True, exist_ok=True)
    fingerprint = store_fingerprint(store)
    train_ds, val_ds = _splits(config, store)
    use_noise = config.uses_view_noise(train_ds.profile)
    batch_size = config.batch_size or train_ds.profile.batch_size
    cfg = config.to_dict()
    if ranks.main:
        (out / "config.json").write_text(json.dumps({**cfg, "view_noise_resolved": use_noise,
                                                     "batch_size_resolved": batch_size,
                                                     "store_fingerprint": fingerprint}, indent=2))

    # the model (initial weights drawn from the seed); appearance only has nothing to train; a
    # frozen g0 network takes the no-objects model's weights (trained first) and keeps them
    torch.manual_seed(config.seed)
    model = GA3CE(config.model).to(device)
    if model.g0_frozen:
        g0_best = g0_run(config, resume, force)
        ranks.barrier()   # rank 0 has written g0's best.pt
        g0 = load_checkpoint(g0_best)["model"]
        missing, unexpected = model.load_state_dict(g0, strict=False)
        if unexpected or any(not k.startswith("pointer.") for k in missing):
            raise CheckpointError(f"{out / 'g0'}: not the no-objects twin of this model ({unexpected or missing})")
        for name, p in model.named_parameters():
            p.requires_grad_(name.startswith("pointer."))
    state: dict[str, Any] = {"config": cfg, "store_fingerprint": fingerprint}
    prior = _mean_angle_deg(val_ds.view, val_ds.gaze) if val_ds else float("nan")
    if not config.model.use_context:
        return _appearance_only(out, state, model, config.epochs, prior) if ranks.main else out

    # the optimiser, the batches (from the store's object counts whether or not this model reads
    # the objects: every arm of an ablation sees the same batches), the per-step schedule
    params = [p for p in model.parameters() if p.requires_grad]
    optimizer = torch.optim.AdamW(params, lr=config.lr, weight_decay=config.weight_decay)
    sampler = BucketBatchSampler(train_ds.obj_count, batch_size, seed=config.seed, batching=config.batching)
    steps_per_epoch = len(sampler)
    total_steps = steps_per_epoch * config.epochs
    warmup_steps = max(1, round(config.warmup_epochs * steps_per_epoch))
    history: list[dict[str, Any]] = []
    best_val = math.inf
    start_epoch = 0

    # continue from last.pt: weights, optimiser, history
    if resume and last_path.exists():
        ckpt = load_checkpoint(last_path)
        problems = check_checkpoint(ckpt, last_path, fingerprint, cfg, force=force)
        for problem in problems:
            log.warning("resuming despite a mismatch (--force): %s", problem)
        model.load_state_dict(ckpt["model"])
        optimizer.load_state_dict(ckpt["optimizer"])
        history = list(ckpt["history"])
        best_val = float(ckpt["best_val"])
        start_epoch = int(ckpt["epoch"]) + 1
        if start_epoch >= config.epochs:
            log.info("%s: all %d epochs are done already", out, config.epochs)
            return out
    elif resume:
        log.warning("%s holds no last.pt: starting a new run", out)

    end_epoch = config.epochs if stop_after_epochs is None else min(config.epochs, start_epoch + stop_after_epochs)
    net = ranks.wrap(model, device)
    for epoch in range(start_epoch, end_epoch):
        sampler.set_epoch(epoch)
        torch.manual_seed(_epoch_seed(config.seed, epoch, 0, ranks.rank))  # dropout
        noise_gen = torch.Generator().manual_seed(_epoch_seed(config.seed, epoch, 1))
        object_gen = torch.Generator().manual_seed(_epoch_seed(config.seed, epoch, 2))
        model.train()
        t0 = time.perf_counter()
        step = epoch * steps_per_epoch
        sum_loss, n_seen = 0.0, 0
        bar = tqdm(sampler.batches(), desc=f"epoch {epoch + 1}/{config.epochs}", unit="batch",
                   disable=not (config.progress and ranks.main), leave=False, dynamic_ncols=True)
        for idx in bar:
            b = train_ds.batch(idx, config.n_max).to(device)
            view = view_noise(b.view, noise_gen, config.view_noise_amplitude) if use_noise else b.view
            b = augment_objects(b, object_gen, config.object_dropout, config.object_frame_dropout, config.object_jitter)
            rows = ranks.share(len(idx))  # the global batch's rows this rank trains on
            n_rows = rows.stop - rows.start
            take = rows if n_rows else slice(0, 1)  # no rows: one at weight 0 keeps the ranks in step
            lr = warmup_cosine_lr(step, total_steps, warmup_steps, config.lr)
            loss = train_step(net, optimizer, b.rows(take), view[take], lr, config.grad_clip,
                              weight=n_rows * ranks.world / len(idx), first_pass_loss=config.first_pass_loss,
                              parts=config.micro_batches if config.model.use_objects else 1)
            step += 1
            sum_loss += loss.item() * n_rows
            n_seen += len(idx)
            bar.set_postfix(loss=f"{loss.item():.4f}", mae=f"{np.degrees(sum_loss / n_seen):.2f}", lr=f"{lr:.2e}")
        seconds = time.perf_counter() - t0
        sum_loss = ranks.sum(sum_loss, device)
        if not ranks.main:
            continue

        # validate, keep the best, checkpoint every epoch, log
        model.eval()
        val = (_mean_angle_deg(predict(model, val_ds, device=device, n_max=config.n_max), val_ds.gaze) if val_ds
               else float("nan"))
        row = {"epoch": epoch, "step": step, "lr": lr, "train_loss": sum_loss / n_seen,
               "train_mae": float(np.degrees(sum_loss / n_seen)), "val_mae": val,
               "val_prior_mae": prior, "seconds": round(seconds, 2),
               "samples_per_s": round(n_seen / seconds, 1)}
        history.append(row)
        improved = not (val >= best_val)  # NaN (no val split) counts as an improvement: best = last
        if improved:
            best_val = val if math.isfinite(val) else best_val
        ckpt = {**state, "epoch": epoch, "model": model.state_dict(), "history": history,
                "best_val": float(best_val)}
        if improved:
            save_checkpoint(best_path, ckpt)
        save_checkpoint(last_path, {**ckpt, "optimizer": optimizer.state_dict()})
        _write_history(history, out)
        msg = (f"epoch {epoch + 1}/{config.epochs}: train MAE {row['train_mae']:.2f} deg, val MAE {val:.2f} deg "
               f"(v prior {prior:.2f}), {row['samples_per_s']:.0f} samples/s")
        if config.progress:
            tqdm.write(msg)
        log.info(msg)
    return out
