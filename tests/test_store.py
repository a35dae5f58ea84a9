import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import zarr

from ga3ce_prep.errors import StoreError
from ga3ce_prep.store import SCHEMA_VERSION, StoreWriter, open_store, verify_store

ATTRS = {"package_version": "0.1.0", "dataset": {"name": "gfie", "root": "/data"},
         "pipeline": {"file": "p.yaml", "sha256": "0" * 64}, "stages": {"depth": {"backend": "sensor"}}}


def _block(rng, n, start):
    counts = rng.integers(0, 5, n)
    frames = {
        "id": [f"f{start + i}" for i in range(n)], "split": rng.integers(0, 3, n),
        "scene": np.zeros(n), "K": np.tile(np.eye(3), (n, 1, 1)), "image_size": np.tile([640, 480], (n, 1)),
        "head_box": rng.random((n, 4)), "body_box": rng.random((n, 4)), "head_pos": rng.random((n, 3)),
        "pose": rng.random((n, 30, 3)), "view": rng.random((n, 3)), "view_source": np.zeros(n, np.int8),
        "head_source": np.zeros(n, np.int8), "gaze": rng.random((n, 3)),
        "eye": rng.random((n, 3)), "gaze_target": rng.random((n, 3)), "obj_count": counts,
    }
    m = int(counts.sum())
    objects = {"xyz": rng.random((m, 3)), "area": rng.integers(1, 100, m), "score": rng.random(m)}
    return frames, objects


def test_store_round_trip_csr(tmp_path):
    rng = np.random.default_rng(0)
    w = StoreWriter(tmp_path / "s.zarr")
    blocks = [_block(rng, n, s) for n, s in [(7, 0), (5000, 7), (3, 5007)]]
    for f, o in blocks:
        w.append_frames(f, o)
    w.append_failures({"frame_id": ["f3"], "stage": ["head"], "error": ["FrameError"],
                       "message": ["no valid depth"], "action": ["dropped"]})
    w.close(ATTRS)
    s = open_store(tmp_path / "s.zarr")
    assert len(s) == 5010
    assert s.attrs["schema_version"] == SCHEMA_VERSION
    all_xyz = np.concatenate([o["xyz"] for _, o in blocks]).astype(np.float32)
    np.testing.assert_array_equal(s.objects["xyz"], all_xyz)
    i = 7 + 123  # a frame of the second block
    f, o = blocks[1]
    start = int(f["obj_count"][:123].sum())
    np.testing.assert_array_equal(s.objects_of(i), o["xyz"][start:start + f["obj_count"][123]].astype(np.float32))
    assert s.frames["id"][i] == "f130"
    assert s.failures["stage"].tolist() == ["head"]
    assert s.split_names == ["train", "val", "test"]
    assert len(s.indices("test")) == int((s.frames["split"] == 2).sum())


def test_store_refuses_other_major_version(tmp_path):
    w = StoreWriter(tmp_path / "s.zarr")
    w.close(ATTRS)
    zarr.open_group(str(tmp_path / "s.zarr"), mode="r+").attrs["schema_version"] = "2.0"
    with pytest.raises(StoreError, match="schema 2.0"):
        open_store(tmp_path / "s.zarr")


def test_store_attrs_validated(tmp_path):
    w = StoreWriter(tmp_path / "s.zarr")
    with pytest.raises(StoreError, match="pipeline"):
        w.close({**ATTRS, "pipeline": {"file": "p.yaml"}})


def test_missing_store_message(tmp_path):
    with pytest.raises(StoreError, match="ga3ce-prep run"):
        open_store(tmp_path / "nope.zarr")


def test_empty_blocks_are_accepted(tmp_path):
    rng = np.random.default_rng(1)
    w = StoreWriter(tmp_path / "s.zarr")
    empty_f, empty_o = _block(rng, 0, 0)
    w.append_frames(empty_f, empty_o)
    f, o = _block(rng, 3, 0)
    w.append_frames(f, o)
    w.append_frames(empty_f, empty_o)
    w.close(ATTRS)
    s = open_store(tmp_path / "s.zarr")
    assert len(s) == 3
    np.testing.assert_array_equal(s.frames["obj_start"], np.concatenate([[0], np.cumsum(f["obj_count"])[:-1]]))


def _small_store(path):
    w = StoreWriter(path, scene_names=["s"])
    w.append_frames(*_block(np.random.default_rng(2), 20, 0))
    w.append_failures({"frame_id": ["f3"], "stage": ["head"], "error": ["FrameError"],
                       "message": ["no valid depth"], "action": ["dropped"]})
    w.close(ATTRS)
    return path


def _flip(b: bytes) -> bytes:
    return b[:len(b) // 2] + bytes([b[len(b) // 2] ^ 0x10]) + b[len(b) // 2 + 1:]


def _retitle(b: bytes) -> bytes:  # valid JSON, one attribute changed
    return b.replace(b'"p.yaml"', b'"q.yaml"')


# damage -> (file in the store, what is done to its bytes (None: deleted), the message expected)
DAMAGE = {
    "deleted chunk": ("frames/pose/c/0/0/0", None, r"array frames/pose, chunk \(0, 0, 0\) \(rows 0-19\): missing"),
    "flipped bit": ("frames/head_pos/c/0/0", _flip,
                    r"array frames/head_pos, chunk \(0, 0\) \(rows 0-19\): its bytes differ from the recorded SHA-256"),
    "truncated chunk": ("objects/xyz/c/0/0", lambda b: b[:9], r"array objects/xyz, chunk \(0, 0\) \(rows 0-\d+\): "
                        r"9 bytes instead of \d+ \(truncated\)"),
    "damaged array metadata": ("frames/view/zarr.json", _flip,
                               r"array frames/view, metadata \(frames/view/zarr.json\)"),
    "damaged root metadata": ("zarr.json", lambda b: b[:40], "the root metadata zarr.json is damaged"),
    "edited root attributes": ("zarr.json", _retitle, r"root attributes \(zarr.json\): differ from their recorded"),
}


@pytest.mark.parametrize("damage", DAMAGE)
def test_integrity_record_names_the_damaged_array_and_chunk(tmp_path, damage):
    from click.testing import CliRunner

    from ga3ce_prep.cli import cli

    path = _small_store(tmp_path / "s.zarr")
    for args in (["info"], ["info", "--verify"]):
        ok = CliRunner().invoke(cli, [*args, str(path)])
        assert ok.exit_code == 0, ok.output
        assert "every one matches its SHA-256" in ok.output
    intact = open_store(path)
    assert intact.verified
    rel, how, message = DAMAGE[damage]
    f = path / rel
    if how is None:
        f.unlink()
    else:
        f.write_bytes(how(f.read_bytes()))
    for verify in ({}, {"verify": True}):  # verified by default
        with pytest.raises(StoreError, match=message):
            open_store(path, **verify)
    for args in (["info"], ["info", "--verify"], ["info", "--json"]):
        res = CliRunner().invoke(cli, [*args, str(path)])
        assert res.exit_code != 0
        assert isinstance(res.exception, StoreError)
        assert re.search(message, str(res.exception))
        assert "rerunning the `ga3ce-prep run` command" in str(res.exception)
    if damage == "deleted chunk":  # what the check is for: unchecked, the chunk reads back as zeros
        assert (open_store(path, verify=False).frames["pose"] == 0).all()
        assert not (intact.frames["pose"] == 0).all()
        res = CliRunner().invoke(cli, ["info", "--no-verify", str(path)])
        assert res.exit_code == 0, res.output
        assert "recorded; not checked (--no-verify)" in res.output


def _installed_cli() -> str:
    """The installed `ga3ce-prep` entry point of this environment."""
    return str(Path(sys.executable).parent / "ga3ce-prep")


# the cases: a chunk of frames/head_pos or frames/id deleted, a bit of an objects/xyz chunk flipped
READER_DAMAGE = {
    "frames/head_pos deleted": ("frames/head_pos/c/0/0", None, "array frames/head_pos, chunk (0, 0) (rows 0-19): "
                                "missing"),
    "frames/id deleted": ("frames/id/c/0", None, "array frames/id, chunk (0,) (rows 0-19): missing"),
    "objects/xyz bit flipped": ("objects/xyz/c/0/0", _flip, "array objects/xyz, chunk (0, 0) (rows 0-"),
}


@pytest.mark.parametrize("damage", READER_DAMAGE)
def test_every_default_read_refuses_a_damaged_store(tmp_path, damage):
    from click.testing import CliRunner

    from ga3ce_prep.cli import cli

    path = _small_store(tmp_path / "s.zarr")
    rel, how, message = READER_DAMAGE[damage]
    f = path / rel
    f.unlink() if how is None else f.write_bytes(how(f.read_bytes()))
    rebuild = f"`ga3ce-prep run --pipeline p.yaml --data /data --out {path}`, with the --set options it had"
    with pytest.raises(StoreError) as e:
        open_store(path)
    assert message in str(e.value) and rebuild in str(e.value)
    for args in (["info", str(path)], ["show", str(path), "f3", "--out", str(tmp_path / "f.png")],
                 ["export", str(path), str(tmp_path / "s.h5")]):
        res = CliRunner().invoke(cli, args)
        assert res.exit_code != 0 and isinstance(res.exception, StoreError), (args, res.output)
        assert message in str(res.exception) and rebuild in str(res.exception)
    assert not (tmp_path / "f.png").exists() and not (tmp_path / "s.h5").exists()
    p = subprocess.run([_installed_cli(), "info", str(path)], capture_output=True, text=True, timeout=120)
    assert p.returncode == 2 and not p.stdout
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {path} is damaged: {message}"), p.stderr
    assert rebuild in lines[0]


@pytest.mark.parametrize("rel", ["objects/xyz/c/0/0", "zarr.json"])
def test_a_truncated_chunk_or_root_metadata_is_one_error_line(tmp_path, rel):
    path = _small_store(tmp_path / "s.zarr")
    f = path / rel
    f.write_bytes(f.read_bytes()[:9])
    p = subprocess.run([sys.executable, "-m", "ga3ce_prep.cli", "info", str(path)], capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 2
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), p.stderr
    assert ("array objects/xyz, chunk (0, 0)" if rel != "zarr.json"
            else "root metadata zarr.json is damaged") in lines[0]


def test_a_store_without_an_integrity_record_cannot_be_verified(tmp_path, caplog):
    from click.testing import CliRunner

    from ga3ce_prep.cli import cli

    path = _small_store(tmp_path / "s.zarr")
    g = zarr.open_group(str(path), mode="r+")
    attrs = dict(g.attrs)
    del attrs["integrity"]
    g.attrs.put(attrs)
    assert len(open_store(path, verify=False)) == 20
    for verify in ({}, {"verify": True}):  # schema 1.4 has a record: its absence is damage
        with pytest.raises(StoreError, match="has no integrity record"):
            open_store(path, **verify)
    g.attrs.put({**attrs, "schema_version": "1.2"})  # a store from before the record: read, with a warning
    s = open_store(path)
    assert len(s) == 20 and not s.verified
    assert "(schema 1.2) has no integrity record, which came with schema 1.3: it is read unchecked" in caplog.text
    res = CliRunner().invoke(cli, ["info", str(path)])
    assert res.exit_code == 0, res.output
    assert "integrity    no record (a store of schema < 1.3)" in res.output
    with pytest.raises(StoreError, match="has no integrity record"):
        verify_store(path)


def test_one_process_verifies_an_unchanged_store_once(tmp_path, monkeypatch):
    import time

    import ga3ce_prep.store as store

    path = _small_store(tmp_path / "s.zarr")
    calls = []
    real = store.verify_store
    monkeypatch.setattr(store, "verify_store", lambda p: calls.append(p) or real(p))
    open_store(path)
    open_store(path)
    assert len(calls) == 2  # its files changed less than SETTLED_S ago: not memoised
    monkeypatch.setattr(store, "SETTLED_S", 0.0)
    time.sleep(0.05)
    open_store(path)
    open_store(path)
    open_store(str(path) + "/")
    assert len(calls) == 3 and all(open_store(path).verified for _ in range(2))
    time.sleep(0.05)
    f = path / "frames/head_pos/c/0/0"
    f.write_bytes(_flip(f.read_bytes()))  # same size and inode; a new mtime and ctime
    with pytest.raises(StoreError, match=r"array frames/head_pos, chunk \(0, 0\)"):
        open_store(path)
    assert len(calls) == 4
