"""Per-frame arrays computed elsewhere (a pose or view estimator run offline), keyed by frame id.

Layout (HDF5 or .npz; documented in docs/pipeline.md):

    frame_id   (N,) str          the dataset's frame ids (`ga3ce-prep info` lists them)
    <values>   (N, ...) float    "pose" (N, 30, 3) metres, smpl+head_30, camera frame;
                                 "view" (N, 3) unit vectors, camera frame

A frame missing from the file raises FrameError for that frame only.
"""
from __future__ import annotations

import threading
from pathlib import Path

import numpy as np

from ..errors import ConfigError, FrameError

_tables: dict[tuple[str, str, int], "PrecomputedTable"] = {}
_lock = threading.Lock()


class PrecomputedTable:
    """An in-memory id -> row table of one array of a precomputed file."""

    def __init__(self, path: Path, name: str, trailing: tuple[int, ...], where: str):
        self.path, self.name = Path(path), name
        if not self.path.is_file():
            raise ConfigError(f"{where}: precomputed file {self.path} not found; write it with the layout in "
                              f"docs/pipeline.md (frame_id (N,) str, {name} (N, {', '.join(map(str, trailing))}))")
        try:
            ids, values = self._read()
        except (OSError, ValueError, KeyError) as e:
            raise ConfigError(f"{where}: cannot read {self.path}: {e}. Expected datasets 'frame_id' (N,) str "
                              f"and {name!r} (N, {', '.join(map(str, trailing))})") from None
        if values.shape[1:] != trailing or len(values) != len(ids):
            raise ConfigError(f"{where}: {self.path}: {name!r} has shape {values.shape} and frame_id {ids.shape}; "
                              f"expected ({len(ids)}, {', '.join(map(str, trailing))})")
        self.values = values.astype(np.float32)
        self.row = {fid: i for i, fid in enumerate(ids.tolist())}

    def _read(self) -> tuple[np.ndarray, np.ndarray]:
        if self.path.suffix == ".npz":
            with np.load(self.path, allow_pickle=False) as z:
                return np.asarray(z["frame_id"]).astype(str), np.asarray(z[self.name])
        import h5py

        with h5py.File(self.path, "r") as f:
            ids = f["frame_id"]
            ids = ids.asstr()[...] if ids.dtype.kind in "OS" else ids[...]
            return np.asarray(ids).astype(str), np.asarray(f[self.name][...])

    def get(self, frame_id: str) -> np.ndarray:
        i = self.row.get(frame_id)
        if i is None:
            raise FrameError(f"frame {frame_id} is not in {self.path} ({self.name})")
        return self.values[i]


def precomputed_table(path: Path, name: str, trailing: tuple[int, ...], where: str) -> PrecomputedTable:
    """The table of `path`, loaded once per process (and again when the file changes)."""
    p = Path(path)
    key = (str(p), name, p.stat().st_mtime_ns if p.exists() else 0)
    with _lock:
        t = _tables.get(key)
        if t is None:
            t = _tables[key] = PrecomputedTable(p, name, trailing, where)
        return t
