"""Store comparisons for the tests: array for array, and byte for byte."""
from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import numpy as np

from ga3ce_prep.store import open_store


def assert_same_store(a: str | Path, b: str | Path, attrs: bool = True) -> None:
    """Every array of stores a and b equal (values and dtypes), the scene names too, and (attrs)
    the root attributes."""
    sa, sb = open_store(a), open_store(b)
    for group in ("frames", "objects", "failures"):
        ga, gb = getattr(sa, group), getattr(sb, group)
        assert sorted(ga) == sorted(gb)
        for name in ga:
            np.testing.assert_array_equal(ga[name], gb[name], err_msg=f"{group}/{name}")
            assert ga[name].dtype == gb[name].dtype
    assert sa.scene_names == sb.scene_names
    if attrs:
        assert sa.attrs == sb.attrs


def store_digests(path: str | Path) -> dict[str, str]:
    """SHA-256 of every file (object) of a store, by its path inside the store: two stores are the
    same bit for bit when these are equal. path: a local directory or an fsspec URL."""
    import fsspec

    fs, root = fsspec.core.url_to_fs(str(path))
    root = root.rstrip("/")
    return {f[len(root) + 1:]: hashlib.sha256(fs.cat_file(f)).hexdigest() for f in sorted(fs.find(root))}


def object_distances(truth: Any, store: Any) -> tuple[np.ndarray, np.ndarray]:
    """Per object of `truth` (a store of the truth's objects, or any store): the distance (m) to the
    nearest object position `store` holds in the same frame (inf if none), and its mask area (px):
    how near a segmenter's positions are to the true objects (`make bench-objects-quality`)."""
    idx = {fid: i for i, fid in enumerate(store.frames["id"])}
    d, area = [], []
    for j, fid in enumerate(truth.frames["id"]):
        T = truth.objects_of(j)
        G = store.objects_of(idx[fid]) if fid in idx else np.zeros((0, 3))
        d.append(np.linalg.norm(T[:, None] - G[None], axis=-1).min(1) if len(G) else np.full(len(T), np.inf))
        area.append(truth.objects["area"][truth.object_slice(j)])
    return np.concatenate(d), np.concatenate(area)
