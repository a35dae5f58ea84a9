import re
import subprocess
import sys

import numpy as np
import pytest
import zarr

from ga3ce_prep.errors import StoreError
from ga3ce_prep.store import SCHEMA_VERSION, StoreWriter, open_store

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
    ok = CliRunner().invoke(cli, ["info", "--verify", str(path)])
    assert ok.exit_code == 0, ok.output
    assert "every one matches its SHA-256" in ok.output
    intact = open_store(path, verify=True)
    rel, how, message = DAMAGE[damage]
    f = path / rel
    if how is None:
        f.unlink()
    else:
        f.write_bytes(how(f.read_bytes()))
    with pytest.raises(StoreError, match=message):
        open_store(path, verify=True)
    res = CliRunner().invoke(cli, ["info", "--verify", str(path)])
    assert res.exit_code != 0
    assert isinstance(res.exception, StoreError)
    assert re.search(message, str(res.exception))
    assert "rerunning the `ga3ce-prep run` command" in str(res.exception)
    if damage == "deleted chunk":  # what --verify is for: without it the chunk reads back as zeros
        assert (open_store(path).frames["pose"] == 0).all()
        assert not (intact.frames["pose"] == 0).all()


@pytest.mark.parametrize("rel", ["objects/xyz/c/0/0", "zarr.json"])
def test_a_truncated_chunk_or_root_metadata_is_one_error_line_without_verify(tmp_path, rel):
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


def test_a_store_without_an_integrity_record_cannot_be_verified(tmp_path):
    path = _small_store(tmp_path / "s.zarr")
    g = zarr.open_group(str(path), mode="r+")
    attrs = dict(g.attrs)
    del attrs["integrity"]
    g.attrs.put(attrs)
    assert len(open_store(path)) == 20
    with pytest.raises(StoreError, match="has no integrity record"):
        open_store(path, verify=True)
