"""Access to the synthetic world's truth side-car (`truth.h5`) for the `oracle` backends.

The file and its reader belong to the synthetic world (`ga3ce_prep.synthetic.truth.TruthReader`);
this module only keeps one open reader per file and process (dask workers included) and turns a
missing file or frame into the pipeline's errors.
"""
from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

from ..errors import ConfigError, FrameError, Ga3ceError

_readers: dict[str, Any] = {}
_lock = threading.Lock()


def _reader(path: str | Path) -> Any:
    key = str(path)
    with _lock:
        r = _readers.get(key)
        if r is None:
            from ..synthetic.truth import TruthReader

            r = _readers[key] = TruthReader(key)
        return r


class _TruthRecord:
    """`truth_record(path, frame_id)`: the synthetic truth of one frame; `.check(path)` before work."""

    def __call__(self, path: str | Path, frame_id: str, maps: bool = True) -> Any:
        """The frame's `TruthFrame`; maps=False skips reading its depth and instance maps."""
        try:
            return _reader(path).get(frame_id, maps=maps)
        except KeyError:
            raise FrameError(f"frame {frame_id} is not in the truth file {path}: the dataset and its "
                             "truth side-car do not match (regenerate both with `ga3ce-prep synth`)") from None

    def object_kinds(self, path: str | Path) -> tuple[str, ...]:
        """Names of the object table's kind codes (code i = name i)."""
        return tuple(_reader(path).object_kinds)

    def check(self, path: str | Path) -> None:
        p = Path(path)
        if not p.is_file():
            raise ConfigError(f"truth file {p} not found: the oracle backends read the synthetic world's "
                              "truth side-car; write the world with `ga3ce-prep synth`, or point the "
                              "backend's `truth` parameter at its truth.h5")
        try:
            _reader(p)
        except Ga3ceError as e:
            raise ConfigError(str(e)) from None


truth_record = _TruthRecord()
