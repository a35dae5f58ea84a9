"""The 3D context store: a plain Zarr v3 group of per-frame arrays (docs/store.md).

Layout (N frames, M objects, F failure records)::

    store.zarr/
      frames/{id, split, scene, K, image_size, head_box, body_box, head_pos, pose, view, gaze,
              eye, gaze_target, obj_start, obj_count}      (N, ...)
      objects/{xyz, area, score}                           (M, ...)  CSR: frame i owns
                                                                     objects[obj_start[i]:][:obj_count[i]]
      failures/{frame_id, stage, error, message, action}   (F,)      action: "dropped" | "degraded"

`split` and `scene` are int codes; their names are in the array's attrs["names"]. Camera frame,
metres, x right, y down, z forward. Unknown values are NaN. The root attrs hold `schema_version`,
the dataset, the pipeline and its hash, per-stage provenance and the package version
(schemas/store.schema.json). Arrays are chunked along the first axis only (Zstd).

Write with `StoreWriter` (appends blocks, memory bounded by one chunk per array); read with
`open_store`, which loads every array into memory (a few KB per frame) and needs no torch.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
import zarr
from zarr.codecs import ZstdCodec

from .errors import StoreError
from .frames import SPLITS
from .skeleton import N_JOINTS

# 1.1: attrs["summary"] holds FinalizeCounts under its own field names; 1.2: frames/view_source
SCHEMA_VERSION = "1.2"
SCHEMA_FILE = Path(__file__).resolve().parent.parent / "schemas" / "store.schema.json"

# name -> (dtype, trailing shape). `str` = variable-length UTF-8.
FRAME_ARRAYS: dict[str, tuple[Any, tuple[int, ...]]] = {
    "id": (str, ()),
    "split": (np.int8, ()),
    "scene": (np.int32, ()),
    "K": (np.float32, (3, 3)),
    "image_size": (np.int32, (2,)),
    "head_box": (np.float32, (4,)),
    "body_box": (np.float32, (4,)),
    "head_pos": (np.float32, (3,)),
    "pose": (np.float32, (N_JOINTS, 3)),
    "view": (np.float32, (3,)),
    "view_source": (np.int8, ()),  # which way v came about; names in the array's attrs["names"]
    "gaze": (np.float32, (3,)),
    "eye": (np.float32, (3,)),
    "gaze_target": (np.float32, (3,)),
    "obj_start": (np.int64, ()),
    "obj_count": (np.int32, ()),
}
OBJECT_ARRAYS: dict[str, tuple[Any, tuple[int, ...]]] = {
    "xyz": (np.float32, (3,)),
    "area": (np.int32, ()),
    "score": (np.float32, ()),
}
FAILURE_ARRAYS: dict[str, tuple[Any, tuple[int, ...]]] = {
    "frame_id": (str, ()),
    "stage": (str, ()),
    "error": (str, ()),
    "message": (str, ()),
    "action": (str, ()),
}
GROUPS = {"frames": FRAME_ARRAYS, "objects": OBJECT_ARRAYS, "failures": FAILURE_ARRAYS}
CHUNK_BYTES = 2 << 20


def _chunk_rows(dtype: Any, trailing: tuple[int, ...]) -> int:
    if dtype is str:
        return 65536
    row = np.dtype(dtype).itemsize * int(np.prod(trailing, dtype=np.int64))
    return int(max(4096, CHUNK_BYTES // max(row, 1)))


class StoreWriter:
    """Append-only writer of a new store at `path` (a local path or an fsspec URL).

    `append_frames(frames, objects)` takes dicts of arrays with the schema's names; `obj_start`
    is filled in by the writer from `obj_count`. Rows are buffered to whole chunks, so memory
    stays bounded whatever the dataset size. `close(attrs)` writes the remaining rows and the
    root attributes (validated against schemas/store.schema.json).
    """

    def __init__(self, path: str | Path, split_names: tuple[str, ...] = SPLITS,
                 scene_names: list[str] | None = None, overwrite: bool = False):
        self.path = str(path)
        self.root = zarr.open_group(self.path, mode="w" if overwrite else "w-")
        self.arrays: dict[str, zarr.Array] = {}
        self.buffers: dict[str, list[np.ndarray]] = {}
        for gname, spec in GROUPS.items():
            for name, (dtype, trailing) in spec.items():
                key = f"{gname}/{name}"
                rows = _chunk_rows(dtype, trailing)
                self.arrays[key] = self.root.create_array(
                    key, shape=(0, *trailing), dtype=dtype, chunks=(rows, *trailing),
                    compressors=ZstdCodec(level=3), fill_value="" if dtype is str else 0)
                self.buffers[key] = []
        self.arrays["frames/split"].attrs["names"] = list(split_names)
        self.scene_names = list(scene_names or [])
        self.n_frames = 0
        self.n_objects = 0

    def scene_code(self, scene: str) -> int:
        """Int code of a scene name, adding it to the table the first time it is seen."""
        try:
            return self.scene_names.index(scene)
        except ValueError:
            self.scene_names.append(scene)
            return len(self.scene_names) - 1

    def _push(self, key: str, value: np.ndarray, force: bool = False) -> None:
        buf = self.buffers[key]
        if value is not None and len(value):
            buf.append(value)
        arr = self.arrays[key]
        n = sum(len(b) for b in buf)
        if n and (force or n >= arr.chunks[0]):
            block = np.concatenate(buf)
            cut = len(block) if force else (len(block) // arr.chunks[0]) * arr.chunks[0]
            arr.append(block[:cut])
            self.buffers[key] = [block[cut:]] if cut < len(block) else []

    def _coerce(self, spec: dict, key: str, name: str, value: Any, n: int) -> np.ndarray:
        dtype, trailing = spec[name]
        a = np.asarray(value).astype(str) if dtype is str else np.asarray(value, dtype=dtype)
        if a.shape != (n, *trailing):
            raise ValueError(f"{key}: expected shape {(n, *trailing)}, got {a.shape}")
        return a

    def append_frames(self, frames: dict[str, np.ndarray], objects: dict[str, np.ndarray]) -> None:
        """Append n frames and their objects (CSR by frames['obj_count'])."""
        n = len(frames["id"])
        counts = np.asarray(frames["obj_count"], np.int64)
        m = int(counts.sum())
        frames = dict(frames)
        frames["obj_start"] = self.n_objects + np.concatenate([[0], np.cumsum(counts)])[:n].astype(np.int64)
        missing = set(FRAME_ARRAYS) - set(frames)
        if missing:
            raise ValueError(f"frames block lacks {sorted(missing)}")
        for name in FRAME_ARRAYS:
            self._push(f"frames/{name}", self._coerce(FRAME_ARRAYS, f"frames/{name}", name, frames[name], n))
        for name in OBJECT_ARRAYS:
            self._push(f"objects/{name}", self._coerce(OBJECT_ARRAYS, f"objects/{name}", name, objects[name], m))
        self.n_frames += n
        self.n_objects += m

    def append_failures(self, failures: dict[str, Any]) -> None:
        """Append failure records: frame_id, stage, error (class name), message, action."""
        n = len(failures["frame_id"])
        for name in FAILURE_ARRAYS:
            self._push(f"failures/{name}", self._coerce(FAILURE_ARRAYS, f"failures/{name}", name, failures[name], n))

    def close(self, attrs: dict[str, Any], view_sources: tuple[str, ...] = ("view",)) -> None:
        """`flush`, then `commit`."""
        self.flush(view_sources)
        self.commit(attrs)

    def flush(self, view_sources: tuple[str, ...] = ("view",)) -> None:
        """Write every buffered row and the arrays' attributes: everything but the root attributes.
        view_sources: the names behind frames/view_source's codes (the view backend's sources)."""
        for key in self.arrays:
            self._push(key, None, force=True)
        self.arrays["frames/scene"].attrs["names"] = list(self.scene_names)
        self.arrays["frames/view_source"].attrs["names"] = list(view_sources)

    def commit(self, attrs: dict[str, Any]) -> None:
        """Write the root attributes (validated first; schema_version is set here) in one write of
        the root metadata, after everything else: until then the store reads as unfinished."""
        attrs = {**attrs, "schema_version": SCHEMA_VERSION}
        validate_store_attrs(attrs)
        self.root.attrs.update(attrs)


def validate_store_attrs(attrs: dict[str, Any]) -> None:
    """Check root attributes against schemas/store.schema.json (raises StoreError naming the key)."""
    import jsonschema

    schema = json.loads(SCHEMA_FILE.read_text())
    try:
        jsonschema.validate(json.loads(json.dumps(attrs)), schema)
    except jsonschema.ValidationError as e:
        where = "/".join(str(p) for p in e.absolute_path) or "(root)"
        raise StoreError(f"store attribute {where}: {e.message}") from None


@dataclass
class ContextStore:
    """A store loaded into memory: `frames[name]` (N, ...), `objects[name]` (M, ...),
    `failures[name]` (F,), root `attrs`, and the names behind the split and scene codes."""

    path: str
    attrs: dict[str, Any]
    frames: dict[str, np.ndarray]
    objects: dict[str, np.ndarray]
    failures: dict[str, np.ndarray]
    split_names: list[str] = field(default_factory=list)
    scene_names: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.frames["id"])

    def indices(self, split: str) -> np.ndarray:
        """Frame indices of one split ("train", "val" or "test")."""
        if split not in self.split_names:
            raise KeyError(f"split {split!r} not in {self.split_names}")
        return np.flatnonzero(self.frames["split"] == self.split_names.index(split))

    def object_slice(self, i: int) -> slice:
        s = int(self.frames["obj_start"][i])
        return slice(s, s + int(self.frames["obj_count"][i]))

    def objects_of(self, i: int) -> np.ndarray:
        """(n_i, 3) object positions of frame i."""
        return self.objects["xyz"][self.object_slice(i)]

    @cached_property
    def usable_objects(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Every frame's usable objects, largest mask first, computed once per store (the trainer's
        datasets share it): xyz (M', 3) float32 metres, area (M',) pixels, start (N,), count (N,)
        int64, CSR like frames/obj_start and obj_count. Objects with a non-finite position, and all
        objects of a frame without a finite head position, are left out."""
        count = self.frames["obj_count"].astype(np.int64)
        start = self.frames["obj_start"].astype(np.int64)
        owner = np.repeat(np.arange(len(count)), count)
        rows = (np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count, count)) + np.repeat(start, count)
        xyz = self.objects["xyz"][rows].astype(np.float32)
        area = self.objects["area"][rows]
        head_ok = np.isfinite(self.frames["head_pos"]).all(1)
        keep = np.isfinite(xyz).all(1) & head_ok[owner]
        order = np.lexsort((-area[keep].astype(np.float64), owner[keep]))
        owner, xyz, area = owner[keep][order], xyz[keep][order], area[keep][order]
        new_count = np.bincount(owner, minlength=len(count)).astype(np.int64)
        return xyz, area, np.cumsum(new_count) - new_count, new_count


def open_store(path: str | Path) -> ContextStore:
    """Load a store into memory as numpy arrays. Raises StoreError if it is missing, unfinished
    or of another major schema version."""
    path = str(path)
    try:
        root = zarr.open_group(path, mode="r")
    except (FileNotFoundError, zarr.errors.GroupNotFoundError) as e:
        raise StoreError(f"no store at {path}: run `ga3ce-prep run ... --out {path}` first") from e
    attrs = dict(root.attrs)
    version = attrs.get("schema_version")
    if version is None:
        raise StoreError(f"{path} has no schema_version: it is not a finished ga3ce-prep store "
                         "(an interrupted run? rerun the same command to resume and finalize it)")
    if str(version).split(".")[0] != SCHEMA_VERSION.split(".")[0]:
        raise StoreError(f"{path} has store schema {version}; this ga3ce-prep reads {SCHEMA_VERSION}. "
                         "Rebuild the store with this version (`ga3ce-prep run`) or install the "
                         "ga3ce-prep release that wrote it")
    groups: dict[str, dict[str, np.ndarray]] = {}
    for gname in GROUPS:
        g = root[gname]
        groups[gname] = {name: np.asarray(g[name][...]) for name in g.array_keys()}
    return ContextStore(path=path, attrs=attrs, frames=groups["frames"], objects=groups["objects"],
                        failures=groups["failures"],
                        split_names=list(root["frames/split"].attrs.get("names", SPLITS)),
                        scene_names=list(root["frames/scene"].attrs.get("names", [])))
