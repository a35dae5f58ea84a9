"""The stage cache: one entry per stage and shard, written atomically, named by its key.

    <work>/cache/<stage>/<key[:2]>/<key>.npz      (<work>: a local directory or a URL)

A key is the SHA-256 of the stage's backend, backend version, parameters, model files' SHA-256,
data files' identity, and its upstream keys (the input stage's key hashes the shard's frames and
their files' identity: path, size, modification time). So a changed parameter changes that
stage's key and its dependents' keys only; everything else is found again. An entry is written to
a temporary file in the same directory, fsynced and renamed into place (then the directory is
fsynced), so a killed run never leaves a half-written entry under a real key. On object storage,
where there is no rename, an entry is one PUT of its whole bytes (a multipart upload above 50 MB):
the store shows the object only once it is complete, so the same holds without temporaries. An
entry that cannot be read back whole (a torn or truncated file, a flipped bit: each member's CRC-32
is checked) is removed with a warning and so computed again, in the same run (graph.py, run.py).
CRC-32 catches accidents, not edits (a tool that rewrites the archive recomputes it), so each entry
also records the SHA-256 of its arrays (`content_digest`, the member `content_sha256`), checked when
it is read: an entry whose arrays no longer match is removed and computed again the same way. An
entry without the member (written before it existed) is read as before, on its CRC-32 alone.
"""
from __future__ import annotations

import hashlib
import io
import json
import logging
import os
import tempfile
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from .faults import fault
from .location import Location, filesystem, is_remote

log = logging.getLogger("ga3ce_prep.pipeline")

# The arrays an entry must hold (pipeline/tasks.py writes them): one without them is damaged, and
# read as missing (then recomputed), like an unreadable one.
ENTRY_ARRAYS: tuple[str, ...] = ("ids", "ok", "fail_idx", "fail_error", "fail_message")
DIGEST = "content_sha256"  # the member holding the SHA-256 of the entry's other arrays (`content_digest`)
STAGE_ARRAYS: dict[str, tuple[str, ...]] = {
    "depth": ("valid_frac", "filled_frac"), "objects": ("count", "n_dropped", "xyz", "area", "score"),
    "head": ("head_pos",), "pose": ("pose",), "view": ("view",)}


def _canon(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _canon(v) for k, v in sorted(obj.items(), key=lambda kv: str(kv[0]))}
    if isinstance(obj, (list, tuple)):
        return [_canon(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return {"dtype": str(obj.dtype), "shape": list(obj.shape),
                "sha": hashlib.sha256(np.ascontiguousarray(obj).tobytes()).hexdigest()}
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, float):
        return repr(obj)  # exact, and NaN-safe
    return obj


def stable_hash(obj: Any) -> str:
    """SHA-256 hex of a canonical JSON form of obj (dicts sorted, arrays by content, floats exact)."""
    return hashlib.sha256(json.dumps(_canon(obj), sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def file_identity(path: str | Path | None) -> list[Any] | None:
    """[path, size, mtime_ns] of a file, [path, None, None] if it is missing, None for no path."""
    if path is None:
        return None
    try:
        st = os.stat(path)
        return [str(path), st.st_size, st.st_mtime_ns]
    except OSError:
        return [str(path), None, None]


def content_digest(arrays: Mapping[str, Any]) -> str:
    """SHA-256 hex of an entry's arrays as they read back: by name (sorted), each array's dtype,
    shape and bytes; the DIGEST member itself left out."""
    h = hashlib.sha256()
    for name in sorted(arrays):
        if name == DIGEST:
            continue
        a = np.asarray(arrays[name])
        h.update(json.dumps([name, a.dtype.str, list(a.shape)]).encode())
        if a.dtype.kind == "O":  # not in an entry (it could not be read back without pickle): hashed all the same
            h.update(repr(a.tolist()).encode())
        else:  # the bytes, without a copy
            h.update(np.ascontiguousarray(a).reshape(-1).view(np.uint8).data)
    return h.hexdigest()


class EntryChanged(ValueError):
    """A cache entry whose arrays differ from its recorded content digest."""


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


class Cache:
    """Stage entries under `root`: a local directory or a URL every worker can reach."""

    def __init__(self, root: Location):
        self.remote = is_remote(root)
        self.root: Location = str(root).rstrip("/") if self.remote else Path(root)
        # fsspec's filesystem (untyped) for a remote cache; a local one (root a Path) has none
        self.fs: Any = filesystem(str(root), "the stage cache") if self.remote else None

    def remove_temporaries(self) -> None:
        """Remove the temporary files a killed run left (only while holding the run lock; a
        remote cache has none)."""
        if isinstance(self.root, Path):
            for tmp in self.root.glob("*/*/.*.tmp"):
                tmp.unlink(missing_ok=True)

    def path(self, stage: str, key: str) -> Location:
        name = f"{stage}/{key[:2]}/{key}.npz"
        return self.root / name if isinstance(self.root, Path) else f"{self.root}/{name}"

    def has(self, stage: str, key: str) -> bool:
        p = self.path(stage, key)
        return p.is_file() if isinstance(p, Path) else self.fs.exists(p)

    def entries(self) -> set[tuple[str, str]]:
        """(stage, key) of every entry, from one listing (a remote cache answers it in a few
        requests, not one per entry)."""
        if isinstance(self.root, Path):
            names = [str(p) for p in self.root.glob("*/*/*.npz")]
        else:
            names = [f for f in self.fs.find(self.root) if f.endswith(".npz")]
        return {(parts[-3], parts[-1][:-len(".npz")]) for parts in (n.rsplit("/", 3) for n in names)}

    def load(self, stage: str, key: str) -> dict[str, np.ndarray] | None:
        """The entry's arrays (without its DIGEST), or None if it is missing, damaged (a bad CRC-32,
        unreadable), lacks its arrays or no longer matches its content digest (then it is removed,
        with a warning)."""
        p = self.path(stage, key)
        source: io.BytesIO | Path
        if isinstance(p, Path):
            source = p
        else:
            try:  # network errors are raised, not taken for a damaged entry
                source = io.BytesIO(self.fs.cat_file(p))
            except FileNotFoundError:
                return None
        try:
            data = source.getvalue() if isinstance(source, io.BytesIO) else source.read_bytes()
            with zipfile.ZipFile(io.BytesIO(data)) as z:
                bad = z.testzip()
            if bad is not None:
                raise zipfile.BadZipFile(f"bad CRC-32 for {bad}")
            with np.load(io.BytesIO(data), allow_pickle=False) as z:
                entry = {k: z[k] for k in z.files}
            missing = [k for k in (*ENTRY_ARRAYS, *STAGE_ARRAYS.get(stage, ())) if k not in entry]
            if missing:
                raise KeyError(f"lacks {missing}")
            recorded = entry.pop(DIGEST, None)
            if recorded is not None and str(recorded) != content_digest(entry):
                raise EntryChanged(f"its arrays differ from their SHA-256 recorded in {DIGEST} (changed after it "
                                   "was written; its CRC-32 matches)")
            return entry
        except FileNotFoundError:
            return None
        except Exception as e:  # whatever a damaged file makes zipfile or numpy raise
            log.warning("cache entry %s is damaged (%s: %s): removed, it is computed again", p, type(e).__name__, e)
            p.unlink(missing_ok=True) if isinstance(p, Path) else self.fs.rm_file(p)
            return None

    def save(self, stage: str, key: str, arrays: Mapping[str, npt.ArrayLike]) -> Location:
        """Write an entry atomically, with the SHA-256 of its arrays (DIGEST): locally a temp file,
        fsync, rename, fsync the directory; remote one PUT of the whole entry."""
        if DIGEST in arrays:
            raise ValueError(f"a cache entry's array may not be named {DIGEST!r}")
        arrays = {**arrays, DIGEST: np.array(content_digest(arrays))}
        p = self.path(stage, key)
        if not isinstance(p, Path):
            buf = io.BytesIO()
            np.savez(buf, allow_pickle=True, **arrays)  # savez's default, named: the arrays are keywords too
            fault("cache.tmp")
            self.fs.pipe_file(p, buf.getvalue())
            fault("cache.saved")
            return p
        p.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{key[:16]}.", suffix=".tmp", dir=p.parent)
        try:
            with os.fdopen(fd, "wb") as f:
                np.savez(f, allow_pickle=True, **arrays)
                f.flush()
                os.fsync(f.fileno())
            fault("cache.tmp")
            os.replace(tmp, p)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        _fsync_dir(p.parent)
        fault("cache.saved")
        return p
