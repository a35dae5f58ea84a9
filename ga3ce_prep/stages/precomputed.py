"""Per-frame arrays computed elsewhere (a pose, view or depth estimator run offline), keyed by frame id.

Layout (HDF5 or .npz; documented in docs/pipeline.md):

    frame_id   (N,) str          the dataset's frame ids (`ga3ce-prep info` lists them)
    <values>   (N, ...) float    "pose" (N, 30, 3) metres, smpl+head_30, camera frame;
                                 "view" (N, 3) unit vectors, camera frame;
                                 "depth" (N, H, W) depth maps at the image resolution

An .npz is read whole (once per process); HDF5 rows are read when asked for, so a file of depth
maps larger than memory works. A frame missing from the file raises FrameError for that frame only.
"""
from __future__ import annotations

import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigError, FrameError

_tables: dict[tuple[str, str, int], PrecomputedTable] = {}
_lock = threading.Lock()


class PrecomputedTable:
    """An id -> row table of one array of a precomputed file. `trailing`: the row shape, an int per
    fixed size, a name (e.g. "H") for a size the file chooses."""

    def __init__(self, path: Path, name: str, trailing: tuple[int | str, ...], where: str):
        self.path, self.name = Path(path), name
        layout = f"{name} (N, {', '.join(map(str, trailing))})"
        if not self.path.is_file():
            raise ConfigError(f"{where}: precomputed file {self.path} not found; write it with the layout in "
                              f"docs/pipeline.md (frame_id (N,) str, {layout})")
        try:
            ids, values = self._read()
        except (OSError, ValueError, KeyError) as e:
            raise ConfigError(f"{where}: cannot read {self.path}: {e}. Expected datasets 'frame_id' (N,) str "
                              f"and {layout}") from None
        shape = tuple(values.shape)
        if (len(shape) != 1 + len(trailing) or len(values) != len(ids)
                or any(isinstance(t, int) and t != n for t, n in zip(trailing, shape[1:]))):
            raise ConfigError(f"{where}: {self.path}: {name!r} has shape {shape} and frame_id {ids.shape}; "
                              f"expected ({len(ids)}, {', '.join(map(str, trailing))})")
        self.values = values  # np.ndarray (npz) or h5py.Dataset (rows read by `get`)
        self.ids: list[str] = ids.tolist()
        self.row = {fid: i for i, fid in enumerate(self.ids)}

    def _read(self) -> tuple[np.ndarray, Any]:
        if self.path.suffix == ".npz":
            with np.load(self.path, allow_pickle=False) as z:
                return np.asarray(z["frame_id"]).astype(str), np.asarray(z[self.name]).astype(np.float32)
        import h5py

        f = h5py.File(self.path, "r")  # kept open for the table's life: rows are read on demand
        try:
            ids = f["frame_id"]
            ids = ids.asstr()[...] if ids.dtype.kind in "OS" else ids[...]
            return np.asarray(ids).astype(str), f[self.name]
        except Exception:
            f.close()
            raise

    def check_first(self, convert: Callable[[str, np.ndarray], Any], usable: Callable[[np.ndarray], bool],
                    n: int = 10) -> None:
        """Before any work: `convert(frame_id, row)` on the first `usable` row among the first `n`; its
        FrameError (a file in the wrong unit, say) becomes a ConfigError that stops the run."""
        for fid in self.ids[:n]:
            row = self.get(fid)
            if usable(row):
                try:
                    convert(fid, row)
                except FrameError as e:
                    raise ConfigError(str(e)) from None
                return

    def get(self, frame_id: str) -> np.ndarray:
        """The frame's row as float32; FrameError if the file does not hold the frame."""
        i = self.row.get(frame_id)
        if i is None:
            raise FrameError(f"frame {frame_id} is not in {self.path} ({self.name})")
        return np.asarray(self.values[i], np.float32)


def precomputed_table(path: Path, name: str, trailing: tuple[int | str, ...], where: str) -> PrecomputedTable:
    """The table of `path`, loaded once per process (and again when the file changes)."""
    p = Path(path)
    key = (str(p), name, p.stat().st_mtime_ns if p.exists() else 0)
    with _lock:
        t = _tables.get(key)
        if t is None:
            t = _tables[key] = PrecomputedTable(p, name, trailing, where)
        return t
