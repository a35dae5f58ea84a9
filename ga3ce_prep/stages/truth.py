"""Access to the synthetic world's truth side-car (`truth.h5`) for the `oracle` backends.

The file and its reader belong to the synthetic world (`ga3ce_prep.synthetic.truth.TruthReader`);
this module keeps one open reader per file and process (dask workers included), turns a missing
file or frame into the pipeline's errors, and declares the parameter every oracle backend shares.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..errors import ConfigError, FrameError, Ga3ceError
from ..params import param

TRUTH_HINT = "write the synthetic world with `ga3ce-prep synth` (it writes truth.h5 at the dataset root)"

_readers: dict[str, Any] = {}
_lock = threading.Lock()


@dataclass(frozen=True, kw_only=True)
class TruthParams:
    """The parameter of every `oracle` backend."""

    truth: Path = param(
        # the synthetic world's truth side-car; {data} is the --data root
        "{data}/truth.h5", file="data", hint=TRUTH_HINT)


def _reader(path: str | Path) -> Any:
    key = str(path)
    with _lock:
        r = _readers.get(key)
        if r is None:
            from ..synthetic.truth import TruthReader

            r = _readers[key] = TruthReader(key)
        return r


def truth_frame(path: str | Path, frame_id: str, maps: bool = True) -> Any:
    """The frame's `TruthFrame`; maps=False skips reading its depth and instance maps."""
    try:
        return _reader(path).get(frame_id, maps=maps)
    except KeyError:
        raise FrameError(f"frame {frame_id} is not in the truth file {path}: the dataset and its "
                         "truth side-car do not match (regenerate both with `ga3ce-prep synth`)") from None


def truth_object_kinds(path: str | Path) -> tuple[str, ...]:
    """Names of the object table's kind codes (code i = name i)."""
    return tuple(_reader(path).object_kinds)


def check_truth_file(path: str | Path) -> None:
    """Before any work: the truth file exists and opens; ConfigError naming the fix otherwise."""
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"truth file {p} not found: the oracle backends read the synthetic world's "
                          "truth side-car; write the world with `ga3ce-prep synth`, or point the "
                          "backend's `truth` parameter at its truth.h5")
    try:
        _reader(p)
    except Ga3ceError as e:
        raise ConfigError(str(e)) from None
