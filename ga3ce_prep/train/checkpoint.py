"""Checkpoints: plain dicts of tensors and plain types, loadable with torch.load(weights_only=True).

A checkpoint holds: format, epoch (last finished, 0-based), model (state_dict), config (the
training configuration as a dict, model config nested under "model"), store_fingerprint (SHA-256 of
the store it was trained on), history (per-epoch rows), best_val (lowest validation MAE, degrees)
and, in `last.pt` only, optimizer (its state_dict) so `--resume` continues exactly.
Writes are atomic (temp file + rename): a killed run never leaves a half-written checkpoint.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import torch

from ..errors import Ga3ceError
from ..model import GA3CE, ModelConfig

FORMAT = "ga3ce-prep/checkpoint/1"
# training options that change the result at most by rounding: allowed to differ on --resume
RESULT_NEUTRAL = frozenset({"store", "out", "device", "threads", "progress", "micro_batches"})


class CheckpointError(Ga3ceError):
    """A checkpoint is missing, unreadable, or does not match the store or configuration."""


def save_checkpoint(path: str | Path, state: dict[str, Any]) -> None:
    """Write `state` (plus the format tag) to `path` atomically."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    torch.save({"format": FORMAT, **state}, tmp)
    with open(tmp, "rb") as f:
        os.fsync(f.fileno())
    os.replace(tmp, path)


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """Read a checkpoint with weights_only=True (no code runs on load). Raises CheckpointError."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} not found (a run folder holds best.pt and last.pt)")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # any unpickling failure means "not our checkpoint"
        raise CheckpointError(f"cannot read checkpoint {path}: {e}") from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != FORMAT:
        raise CheckpointError(f"{path} is not a ga3ce-prep checkpoint (format {FORMAT})")
    check_model(ckpt, path)
    return ckpt


def check_model(ckpt: dict[str, Any], path: str | Path) -> None:
    """CheckpointError naming the file and the first difference unless the checkpoint's weights
    are exactly those of the model its configuration (`config.model`) describes: a checkpoint
    whose weights come from another model configuration (edited, assembled from two runs, or
    written by another version) is refused before any work."""
    fix = "use the best.pt or last.pt its run folder wrote, or retrain with the configuration you want"
    try:
        cfg = ModelConfig.from_dict(ckpt["config"]["model"])
    except (KeyError, TypeError, ValueError) as e:
        raise CheckpointError(f"{path}: config.model is not a GA3CE model configuration ({e}); {fix}") from None
    weights = ckpt.get("model")
    if not isinstance(weights, dict):
        raise CheckpointError(f"{path}: 'model' holds a {type(weights).__name__}, not the model's weights; {fix}")
    want = {k: tuple(v.shape) for k, v in GA3CE(cfg).state_dict().items()}
    have = {k: tuple(getattr(v, "shape", ())) for k, v in weights.items()}
    diff = ([f"weight {k} is missing" for k in sorted(want.keys() - have.keys())]
            + [f"weight {k} is not in this model" for k in sorted(have.keys() - want.keys())]
            + [f"weight {k} has shape {list(have[k])}, the configuration needs {list(want[k])}"
               for k in sorted(want.keys() & have.keys()) if want[k] != have[k]])
    if diff:
        raise CheckpointError(f"{path}: the weights are not those of its config.model ({diff[0]}"
                              f"{f'; {len(diff) - 1} more differences' if len(diff) > 1 else ''}): they come from "
                              f"another model configuration; {fix}")


def config_differences(saved: dict[str, Any], current: dict[str, Any], prefix: str = "") -> list[str]:
    """Human-readable differences between two config dicts, ignoring RESULT_NEUTRAL keys."""
    out = []
    for key in sorted(set(saved) | set(current)):
        if not prefix and key in RESULT_NEUTRAL:
            continue
        a, b = saved.get(key, "<absent>"), current.get(key, "<absent>")
        if isinstance(a, dict) and isinstance(b, dict):
            out += config_differences(a, b, f"{prefix}{key}.")
        elif a != b and not (isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)) and list(a) == list(b)):
            out.append(f"{prefix}{key}: checkpoint {a!r}, now {b!r}")
    return out


def _resolved(saved: dict[str, Any]) -> dict[str, Any]:
    """A saved training config with its model config as this version reads it (an alias saved
    before the fixed design names resolved to the design it named then, missing keys filled as
    `ModelConfig.from_dict` fills them), so that only real differences count; as saved if unreadable."""
    model = saved.get("model")
    if not isinstance(model, dict):
        return saved
    try:
        return {**saved, "model": ModelConfig.from_dict(model).to_dict()}
    except (TypeError, ValueError):
        return saved


def check_checkpoint(ckpt: dict[str, Any], path: str | Path, fingerprint: str | None = None,
                     config: dict[str, Any] | None = None, force: bool = False) -> list[str]:
    """Refuse a checkpoint trained on another store or with another configuration.

    Returns the list of mismatches (empty when all match). Raises CheckpointError naming them
    unless `force`, in which case the caller may warn and go on.
    """
    problems = []
    if fingerprint is not None and ckpt.get("store_fingerprint") != fingerprint:
        problems.append(f"store fingerprint: checkpoint {str(ckpt.get('store_fingerprint'))[:12]}..., "
                        f"this store {fingerprint[:12]}... (a different or rebuilt store)")
    if config is not None:
        problems += config_differences(_resolved(ckpt.get("config", {})), config)
    if problems and not force:
        raise CheckpointError(f"checkpoint {path} does not match:\n  " + "\n  ".join(problems)
                              + "\nUse another --out (or --checkpoint), or pass --force to use it anyway")
    return problems


def build_model(ckpt: dict[str, Any]) -> GA3CE:
    """The GA3CE model a checkpoint describes, with its weights loaded (eval mode, CPU)."""
    model = GA3CE(ModelConfig.from_dict(ckpt["config"]["model"]))
    model.load_state_dict(ckpt["model"])
    return model.eval()


def run_design(path: str | Path) -> str | None:
    """The fixed design (model/methods.py) of the model a run trained: `path` is its run folder or
    one of its checkpoints. Read from the run's config.json, else from the checkpoint (`best.pt` of a
    folder); an alias saved before the fixed names is read as the design it named then. None when
    the run has neither yet."""
    path = Path(path)
    run, ckpt = (path, path / "best.pt") if path.is_dir() or not path.suffix else (path.parent, path)
    if (run / "config.json").is_file():
        saved = json.loads((run / "config.json").read_text())["model"]
    elif ckpt.is_file():
        saved = load_checkpoint(ckpt)["config"]["model"]
    else:
        return None
    return ModelConfig.from_dict(saved).method
