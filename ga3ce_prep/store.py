"""The 3D context store: a plain Zarr v3 group of per-frame arrays (docs/store.md).

Layout (N frames, M objects, F failure records)::

    store.zarr/
      frames/{id, split, scene, K, image_size, head_box, body_box, head_pos, head_source, pose,
              view, view_source, gaze, eye, gaze_target, obj_start, obj_count}      (N, ...)
      objects/{xyz, area, score}                           (M, ...)  CSR: frame i owns
                                                                     objects[obj_start[i]:][:obj_count[i]]
      failures/{frame_id, stage, error, message, action}   (F,)      action: "dropped" | "degraded"

`split`, `scene`, `head_source` and `view_source` are int codes; their names are in the array's
attrs["names"] (a `*_source` names the way each frame's value came about: the stage backend's
`sources`). Camera frame,
metres, x right, y down, z forward. Unknown values are NaN. The root attrs hold `schema_version`,
the dataset, the pipeline and its hash, per-stage provenance, the package version
(ga3ce_prep/schemas/store.schema.json) and the integrity record: the size and SHA-256 of every other file of
the store, and a digest of the root attributes themselves (`verify_store` checks it). Arrays are
chunked along the first axis only (Zstd).

Write with `StoreWriter` (appends blocks, memory bounded by one chunk per array); read with
`open_store`, which first checks every file against the integrity record (`verify=False` skips
that), then loads every array into memory (a few KB per frame) and needs no torch; or with
`open_lazy`, which loads only the columns that choose frames and reads the rest for the rows
asked for (`LazyStore.rows`: a store of any size, a block of frames at a time).
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
import zarr
from zarr.codecs import ZstdCodec

from . import bundled
from .errors import StoreError
from .frames import SPLITS
from .skeleton import N_JOINTS

log = logging.getLogger("ga3ce_prep.store")

# 1.1: attrs["summary"] holds FinalizeCounts under its own field names; 1.2: frames/view_source;
# 1.3: attrs["integrity"]; 1.4: frames/head_source
SCHEMA_VERSION = "1.4"
SOURCE_STAGES: tuple[str, ...] = ("head", "view")  # stages whose per-frame source is stored (frames/<stage>_source)
# The root attributes of a store from its creation (`StoreWriter`) to its commit: ours, unfinished
# (a rerun may replace it; pipeline/run.py refuses to replace a Zarr store with other attributes).
UNFINISHED = {"ga3ce_prep": "unfinished"}

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
    "head_source": (np.int8, ()),  # which way t_object came about; names in the array's attrs["names"]
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
REBUILD = ("rebuild the store by rerunning the `ga3ce-prep run` command that wrote it (its work directory's "
           "cache makes that quick), or restore a copy")
RECORD_SINCE = (1, 3)  # the first schema version whose stores carry the integrity record


def _chunk_rows(dtype: Any, trailing: tuple[int, ...]) -> int:
    if dtype is str:
        return 65536
    row = np.dtype(dtype).itemsize * int(np.prod(trailing, dtype=np.int64))
    return int(max(4096, CHUNK_BYTES // max(row, 1)))


class StoreWriter:
    """Append-only writer of a new store at `path` (a local path or an fsspec URL).

    `append_frames(frames, objects)` takes dicts of arrays with the schema's names; `obj_start`
    is filled in by the writer from `obj_count`. Rows are buffered to whole chunks, so memory
    stays bounded whatever the dataset size. `close(attrs)` writes the remaining rows, then the
    root attributes (validated against ga3ce_prep/schemas/store.schema.json) with the integrity record of
    every file written.
    """

    def __init__(self, path: str | Path, split_names: tuple[str, ...] = SPLITS,
                 scene_names: list[str] | None = None, overwrite: bool = False):
        self.path = str(path)
        self.root = zarr.open_group(self.path, mode="w" if overwrite else "w-")
        self.root.attrs.put(dict(UNFINISHED))  # replaced by `commit`
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

    def _push(self, key: str, value: np.ndarray | None, force: bool = False) -> None:
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

    def close(self, attrs: dict[str, Any], sources: dict[str, tuple[str, ...]] | None = None) -> None:
        """`flush`, then `commit`."""
        self.flush(sources)
        self.commit(attrs)

    def flush(self, sources: dict[str, tuple[str, ...]] | None = None) -> None:
        """Write every buffered row and the arrays' attributes: everything but the root attributes.
        sources: per stage of SOURCE_STAGES the names behind frames/<stage>_source's codes (its
        backend's sources; default: the stage's name alone)."""
        for key in self.arrays:
            self._push(key, None, force=True)
        self.arrays["frames/scene"].attrs["names"] = list(self.scene_names)
        for stage in SOURCE_STAGES:
            self.arrays[f"frames/{stage}_source"].attrs["names"] = list((sources or {}).get(stage, (stage,)))

    def commit(self, attrs: dict[str, Any]) -> None:
        """Write the root attributes (validated first; schema_version and the integrity record, the
        digests of every file `flush` left, are set here) in one write of the root metadata, after
        everything else: until then the store reads as unfinished."""
        attrs = json.loads(json.dumps({**attrs, "schema_version": SCHEMA_VERSION}))  # as they will read back
        attrs["integrity"] = {"algorithm": "sha256", "files": file_digests(self.path)}
        attrs["integrity"]["attributes"] = _attributes_digest(attrs)
        validate_store_attrs(attrs)
        self.root.attrs.put(attrs)


def _fs(path: str) -> tuple[Any, str]:
    """(fsspec filesystem, root path in it) of a local path or an fsspec URL."""
    from fsspec.core import url_to_fs

    return url_to_fs(path)


def file_digests(path: str | Path) -> dict[str, list[Any]]:
    """[size, SHA-256 hex] of every file of the store at `path` by its path in the store ("/"
    separated), except the root zarr.json (which holds them) and hidden files."""
    fs, root = _fs(str(path))
    out: dict[str, list[Any]] = {}
    for f in sorted(fs.find(root)):
        rel = f[len(root):].lstrip("/")
        if rel == "zarr.json" or any(part.startswith(".") for part in rel.split("/")):
            continue
        data = fs.cat_file(f)
        out[rel] = [len(data), hashlib.sha256(data).hexdigest()]
    return out


def _attributes_digest(attrs: dict[str, Any]) -> str:
    """SHA-256 of the root attributes' canonical JSON, leaving out attrs["integrity"]["attributes"]."""
    record = {k: v for k, v in attrs.get("integrity", {}).items() if k != "attributes"}
    body = json.dumps({**attrs, "integrity": record}, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(body.encode()).hexdigest()


def _open_root(path: str) -> tuple[zarr.Group, dict[str, Any]]:
    """The store's root group and attributes; StoreError if there is none or its zarr.json is damaged."""
    try:
        root = zarr.open_group(path, mode="r")
        return root, dict(root.attrs)
    except (FileNotFoundError, zarr.errors.GroupNotFoundError) as e:
        raise StoreError(f"no store at {path}: run `ga3ce-prep run ... --out {path}` first") from e
    except Exception as e:  # whatever a damaged zarr.json makes zarr raise
        raise StoreError(f"{path}: the root metadata zarr.json is damaged ({type(e).__name__}: {e}); "
                         f"{REBUILD}") from None


def _chunk_name(fs: Any, root: str, rel: str) -> str:
    """What a file of the store is: "array frames/pose, chunk (3, 0, 0) (rows 17475-23299)",
    "array frames/pose, metadata (zarr.json)" or "group frames, metadata (zarr.json)"."""
    parts = rel.split("/")
    if parts[-1] == "zarr.json":
        node = "/".join(parts[:-1])
        return f"{'group' if node in GROUPS else 'array'} {node}, metadata ({rel})"
    if "c" not in parts:
        return f"file {rel}"
    at = parts.index("c")
    array, index = "/".join(parts[:at]), parts[at + 1:]
    rows = ""
    try:
        meta = json.loads(fs.cat_file(f"{root}/{array}/zarr.json"))
        n = int(meta["chunk_grid"]["configuration"]["chunk_shape"][0])
        first = int(index[0]) * n
        rows = f" (rows {first}-{min(first + n, int(meta['shape'][0])) - 1})"
    except Exception:  # the array's metadata is damaged too: it is reported itself
        pass
    return f"array {array}, chunk ({', '.join(index)}{',' if len(index) == 1 else ''}){rows}"


def store_problems(path: str | Path) -> list[str]:
    """What differs between the store at `path` and its integrity record, one line per damaged file
    naming the array and the chunk (empty: intact). StoreError when the root metadata cannot be read
    or the store has no record."""
    path = str(path)
    _, attrs = _open_root(path)
    record = attrs.get("integrity")
    if not isinstance(record, dict) or not isinstance(record.get("files"), dict):
        raise StoreError(f"{path} has no integrity record (schema {attrs.get('schema_version')}; the record came "
                         f"with schema 1.3): it cannot be verified; rebuild it with this ga3ce-prep "
                         "(`ga3ce-prep run`, the same command) to give it one")
    problems = []
    if record.get("attributes") != _attributes_digest(attrs):
        problems.append("root attributes (zarr.json): differ from their recorded SHA-256")
    files: dict[str, list[Any]] = record["files"]
    fs, root = _fs(path)
    present = file_digests(path)
    for rel in sorted(set(files) | set(present)):
        want, got = files.get(rel), present.get(rel)
        if want == got:
            continue
        if want is None:
            what = "not in the integrity record (a file added after finalize)"
        elif got is None:
            what = "missing (it would read back as fill values)"
        elif got[0] != want[0]:
            what = f"{got[0]} bytes instead of {want[0]} ({'truncated' if got[0] < want[0] else 'grown'})"
        else:
            what = "its bytes differ from the recorded SHA-256 (changed in place)"
        problems.append(f"{_chunk_name(fs, root, rel)}: {what}")
    return problems


def verify_store(path: str | Path) -> None:
    """Check every file of the store at `path` against its integrity record (`store_problems`);
    StoreError naming each damaged array and chunk, and the fix."""
    problems = store_problems(path)
    if problems:
        try:
            attrs = _open_root(str(path))[1]
        except StoreError:
            attrs = None
        raise _damaged(str(path), problems, attrs)


# A local store verified intact in this process: its real path -> the stat of its files then
# (`_stat_signature`). `open_store` verifies it again only when a file changed, appeared or went.
_verified: dict[str, tuple] = {}
SETTLED_S = 2.0  # files changed more recently than this are not memoised (timestamps are coarse)


def _stat_signature(path: str) -> tuple[str, tuple] | None:
    """(real path, every file's path, size, inode, mtime and ctime) of a local store whose files all
    settled (unchanged for SETTLED_S); None for a remote store or one changed that recently. A write
    changes the ctime, which a user cannot set back, so an unchanged signature is unchanged files."""
    from fsspec.implementations.local import LocalFileSystem

    fs, root = _fs(path)
    if not isinstance(fs, LocalFileSystem):
        return None
    root = os.path.realpath(root)
    recent = time.time_ns() - int(SETTLED_S * 1e9)
    files = []
    for dirpath, _, names in os.walk(root):
        for name in names:
            f = os.path.join(dirpath, name)
            try:
                st = os.stat(f)
            except OSError:  # gone meanwhile: verify_store says what is missing
                return None
            if max(st.st_mtime_ns, st.st_ctime_ns) > recent:
                return None
            files.append((os.path.relpath(f, root), st.st_size, st.st_ino, st.st_mtime_ns, st.st_ctime_ns))
    return root, tuple(sorted(files))


def _verify_once(path: str) -> None:
    """`verify_store`, unless this process found the store intact before and none of its files
    changed since (`_stat_signature`)."""
    signature = _stat_signature(path)
    if signature is not None and _verified.get(signature[0]) == signature[1]:
        return
    verify_store(path)
    if signature is not None:
        _verified[signature[0]] = signature[1]


def rebuild_hint(path: str, attrs: dict[str, Any] | None = None) -> str:
    """How to rebuild the store at `path`: REBUILD, with the command as its root attributes record it
    (pipeline file, or its bundled name; dataset root, --limit) when they are readable."""
    if attrs is None:
        return REBUILD
    try:
        pipeline, root = attrs["pipeline"]["file"], attrs["dataset"]["root"]
        limit = (attrs.get("run") or {}).get("limit")
    except (KeyError, TypeError):
        return REBUILD
    pipeline = bundled.name_of(pipeline) or pipeline
    command = f"ga3ce-prep run --pipeline {pipeline} --data {root} --out {path}{f' --limit {limit}' if limit else ''}"
    return REBUILD.replace(", or restore", f": `{command}`, with the --set options it had; or restore")


def _damaged(path: str, problems: list[str], attrs: dict[str, Any] | None = None) -> StoreError:
    shown = "; ".join(problems[:10]) + (f"; ... {len(problems) - 10} more" if len(problems) > 10 else "")
    return StoreError(f"{path} is damaged: {shown}; {rebuild_hint(path, attrs)}")


def validate_store_attrs(attrs: dict[str, Any]) -> None:
    """Check root attributes against ga3ce_prep/schemas/store.schema.json (raises StoreError naming the key)."""
    import jsonschema

    schema = bundled.schema("store")
    try:
        jsonschema.validate(json.loads(json.dumps(attrs)), schema)
    except jsonschema.ValidationError as e:
        where = "/".join(str(p) for p in e.absolute_path) or "(root)"
        raise StoreError(f"store attribute {where}: {e.message}") from None


@dataclass
class ContextStore:
    """A store loaded into memory: `frames[name]` (N, ...), `objects[name]` (M, ...),
    `failures[name]` (F,), root `attrs`, and the names behind the split, scene and source codes
    (`source_names[stage]`: frames/<stage>_source's, for the stages of SOURCE_STAGES the store has);
    `verified`: every file matched the integrity record when it was opened."""

    path: str
    attrs: dict[str, Any]
    frames: dict[str, np.ndarray]
    objects: dict[str, np.ndarray]
    failures: dict[str, np.ndarray]
    split_names: list[str] = field(default_factory=list)
    scene_names: list[str] = field(default_factory=list)
    source_names: dict[str, list[str]] = field(default_factory=dict)
    verified: bool = False  # checked against its integrity record when opened

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


def _version(version: Any) -> tuple[int, ...]:
    """(major, minor) of a schema version; SCHEMA_VERSION's when it cannot be parsed."""
    try:
        return tuple(int(x) for x in str(version).split("."))
    except ValueError:
        return tuple(int(x) for x in SCHEMA_VERSION.split("."))


def _open_checked(path: str, verify: bool) -> tuple[zarr.Group, dict[str, Any], bool]:
    """The root group and attributes of a finished store of this major schema version, checked against
    its integrity record (`verify`; `open_store`'s rules), and whether it was."""
    root, attrs = _open_root(path)
    version = attrs.get("schema_version")
    if version is None:
        raise StoreError(f"{path} has no schema_version: it is not a finished ga3ce-prep store "
                         "(an interrupted run? rerun the same command to resume and finalize it)")
    if str(version).split(".")[0] != SCHEMA_VERSION.split(".")[0]:
        raise StoreError(f"{path} has store schema {version}; this ga3ce-prep reads {SCHEMA_VERSION}. "
                         "Rebuild the store with this version (`ga3ce-prep run`) or install the "
                         "ga3ce-prep release that wrote it")
    if verify and "integrity" not in attrs and _version(version) < RECORD_SINCE:
        log.warning("%s (schema %s) has no integrity record, which came with schema 1.3: it is read unchecked; "
                    "rebuild it with this ga3ce-prep (`ga3ce-prep run`) to give it one", path, version)
        return root, attrs, False
    if verify:
        _verify_once(path)
    return root, attrs, verify


def _code_names(root: zarr.Group, arrays: dict[str, Any]) -> tuple[list[str], list[str], dict[str, list[str]]]:
    """The names behind the split, scene and source codes (`ContextStore`'s split_names, scene_names,
    source_names); `arrays`: the store's frame arrays, by name (which source arrays it has)."""
    split_names = _names(root["frames/split"], SPLITS)
    scene_names = _names(root["frames/scene"], ())
    source_names = {st: _names(root[f"frames/{st}_source"], ()) for st in SOURCE_STAGES if f"{st}_source" in arrays}
    return split_names, scene_names, source_names


def open_store(path: str | Path, verify: bool = True) -> ContextStore:
    """Load a store into memory as numpy arrays. Raises StoreError if it is missing, unfinished,
    of another major schema version, or damaged: any file that differs from the integrity record
    (`verify_store`, naming the array and the chunk, and the command that rebuilds it). A store of
    schema < 1.3 has no record: it is read with a warning. `verify=False` skips the check (only a
    file that cannot be read is then refused, naming its array, and its chunk when the record can
    tell); a process that opens one local store several times checks it once while its files stay
    unchanged. `open_lazy` opens a store without loading it."""
    path = str(path)
    root, attrs, verified = _open_checked(path, verify)
    groups: dict[str, dict[str, np.ndarray]] = {g: {} for g in GROUPS}
    key = ""
    try:
        for gname in GROUPS:
            key = gname
            g = root[gname]
            if not isinstance(g, zarr.Group):
                raise TypeError(f"{gname} is an array, not a group")
            for name, array in g.arrays():
                key = f"{gname}/{name}"
                groups[gname][name] = np.asarray(array[...])
        key = "frames (the names of its codes)"
        split_names, scene_names, source_names = _code_names(root, groups["frames"])
    except Exception as e:  # whatever a damaged chunk or zarr.json makes zarr raise
        raise _unreadable(path, key, e) from None
    return ContextStore(path=path, attrs=attrs, frames=groups["frames"], objects=groups["objects"],
                        failures=groups["failures"], split_names=split_names, scene_names=scene_names,
                        source_names=source_names, verified=verified)


# the frame arrays `LazyStore` holds in memory: what frames are chosen by, and where their objects are
INDEX_ARRAYS: tuple[str, ...] = ("id", "split", "scene", "obj_start", "obj_count")


@dataclass
class LazyStore:
    """A store opened without loading it (`open_lazy`): in memory only the frame arrays that choose
    frames and find their objects (INDEX_ARRAYS: `index[name]`, (N,), a few tens of bytes per
    frame); every other array is read for the rows asked for (`rows`), chunk by chunk. Codes'
    names and `verified` as in `ContextStore`."""

    path: str
    attrs: dict[str, Any]
    root: zarr.Group
    index: dict[str, np.ndarray]
    split_names: list[str] = field(default_factory=list)
    scene_names: list[str] = field(default_factory=list)
    source_names: dict[str, list[str]] = field(default_factory=dict)
    verified: bool = False

    def __len__(self) -> int:
        return len(self.index["id"])

    def rows(self, rows: np.ndarray) -> ContextStore:
        """The frames `rows` (k,) int (store rows, in the order given) and their objects as an in-memory
        ContextStore of k frames (its obj_start counts its own objects; no failures): only the chunks
        holding them are read. StoreError naming the array when one cannot be read."""
        rows = np.asarray(rows, np.int64)
        count = self.index["obj_count"][rows].astype(np.int64)
        start = self.index["obj_start"][rows].astype(np.int64)
        objs = np.repeat(start - np.cumsum(count) + count, count) + np.arange(int(count.sum()))
        frames: dict[str, np.ndarray] = {}
        objects: dict[str, np.ndarray] = {}
        key = ""
        try:
            for group, out, sel in (("frames", frames, rows), ("objects", objects, objs)):
                g = self.root[group]
                assert isinstance(g, zarr.Group)  # _open_checked's store: open_lazy read its index from it
                for name, array in g.arrays():
                    key = f"{group}/{name}"
                    out[name] = (np.asarray(array.oindex[sel]) if len(sel)
                                 else np.zeros((0, *array.shape[1:]), array.dtype))
        except Exception as e:  # whatever a damaged chunk makes zarr raise
            raise _unreadable(self.path, key, e) from None
        frames["obj_start"] = np.cumsum(count) - count
        return ContextStore(path=self.path, attrs=self.attrs, frames=frames, objects=objects, failures={},
                            split_names=self.split_names, scene_names=self.scene_names,
                            source_names=self.source_names, verified=self.verified)


def open_lazy(path: str | Path, verify: bool = True) -> LazyStore:
    """Open a store without loading its arrays (`LazyStore`): checked as `open_store` checks it (the
    integrity record hashes every file once, holding one file at a time), then only INDEX_ARRAYS read."""
    path = str(path)
    root, attrs, verified = _open_checked(path, verify)
    key = ""
    try:
        index = {}
        for name in INDEX_ARRAYS:
            key = f"frames/{name}"
            array = root[key]
            assert isinstance(array, zarr.Array), f"{key} is a group"
            index[name] = np.asarray(array[...])
        frames = root["frames"]
        assert isinstance(frames, zarr.Group), "frames is an array"
        key = "frames (the names of its codes)"
        split_names, scene_names, source_names = _code_names(root, dict(frames.arrays()))
    except Exception as e:  # whatever a damaged chunk or zarr.json makes zarr raise
        raise _unreadable(path, key, e) from None
    return LazyStore(path=path, attrs=attrs, root=root, index=index, split_names=split_names,
                     scene_names=scene_names, source_names=source_names, verified=verified)


def _names(node: zarr.Array | zarr.Group, default: tuple[str, ...]) -> list[str]:
    """The `names` attribute of a coded array (the names of its codes), default when it has none."""
    names: Any = node.attrs.get("names", default)  # JSON: a list of strings as the writer put it
    return list(names)


def _unreadable(path: str, key: str, error: Exception) -> StoreError:
    """The error for a store whose `key` cannot be read: the damaged files by the integrity record
    when it has one, else the array and zarr's error."""
    try:
        problems = store_problems(path)
    except StoreError:
        problems = []
    try:
        attrs = _open_root(path)[1]
    except StoreError:
        attrs = None
    return _damaged(path, problems or [f"{key} cannot be read ({type(error).__name__}: {error})"], attrs)
