"""`run_pipeline` end to end on the synthetic world: store contents, kill-and-resume, partial
recomputation, the lock, sharding/worker invariance, bad inputs, and the store commands info/show/export."""
import csv
import os
import re
import shutil
import signal
import struct
import subprocess
import sys
import zipfile
from pathlib import Path

import h5py
import numpy as np
import pytest
import zarr
from click.testing import CliRunner

from ga3ce_prep.cli import cli
from ga3ce_prep.errors import DatasetFormatError, StoreError
from ga3ce_prep.pipeline import run_pipeline
from ga3ce_prep.pipeline.finalize import FinalizeCounts, shard_block
from ga3ce_prep.pipeline.lock import RunLock
from ga3ce_prep.pipeline.tasks import Shard
from ga3ce_prep.stages import STAGES
from ga3ce_prep.store import open_store
from ga3ce_prep.testing.stores import assert_same_store
from ga3ce_prep.testing.worlds import SMALL

PIPE = "synthetic"
SHARD = ["run.shard_size=3"]


def _run(data, out, extra=(), **kw):
    return run_pipeline(PIPE, data, out, overrides=[*SMALL, *SHARD, *extra], progress=False, **kw)


@pytest.fixture(scope="module")
def reference(synth_world, tmp_path_factory):
    out = tmp_path_factory.mktemp("ref") / "ref.zarr"
    summary = _run(synth_world, out)
    return out, summary


def test_store_contents_and_provenance(synth_world, reference):
    out, summary = reference
    s = open_store(out)
    assert summary.counts.frames_total == 12
    assert summary.counts.frames_kept == len(s) == 12
    assert summary.n_shards == 4
    assert not summary.counts.failures
    assert set(s.split_names) == {"train", "val", "test"}
    assert len(s.scene_names) == 3
    assert s.frames["obj_count"].sum() == len(s.objects["xyz"]) == summary.counts.objects > 0
    np.testing.assert_array_equal(s.frames["obj_start"][1:], np.cumsum(s.frames["obj_count"])[:-1])
    assert np.isfinite(s.frames["pose"]).all()
    assert np.isfinite(s.frames["head_pos"]).all()
    np.testing.assert_allclose(np.linalg.norm(s.frames["view"], axis=1), 1, atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(s.frames["gaze"], axis=1), 1, atol=1e-5)
    st = s.attrs["stages"]
    assert st["pose"]["backend"] == "oracle"
    assert st["pose"]["oracle"]
    assert st["view"]["oracle"]
    assert st["objects"]["backend"] == "geometric"
    assert not st["objects"]["oracle"]
    assert st["view"]["params"]["mean_error_deg"] == 20.0
    assert st["objects"]["params"]["stride"] == 1
    assert s.attrs["dataset"]["name"] == "gfie"
    world = s.attrs["dataset"]["synthetic"]  # the truth.h5 at the root: how the world was made
    assert world["protocol"] == "unseen-rooms: one session per room, split by room"
    assert (world["sessions_per_room"], world["rooms"], world["seed"]) == (1, 3, 5)
    assert len(s.attrs["pipeline"]["sha256"]) == 64
    assert s.attrs["summary"]["frames_kept"] == 12
    text = summary.format()
    assert "12 kept of 12" in text
    assert "objects" in text
    assert "depth" in text


def _cli_run(data, out, fault=None):
    env = {**os.environ, "GA3CE_FAULT": fault or "", "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "ga3ce_prep.cli", "run", "-p", PIPE, "-d", str(data), "-o", str(out), "-q"]
    for o in (*SMALL, *SHARD):
        cmd += ["--set", o]
    return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)


@pytest.mark.parametrize("fault", ["cache.tmp:3", "cache.saved:9", "finalize.shard:2", "finalize.swap:1"])
def test_sigkill_then_same_command_resumes_to_an_identical_store(synth_world, reference, tmp_path, fault):
    out = tmp_path / "s.zarr"
    p = _cli_run(synth_world, out, fault)
    assert p.returncode == -signal.SIGKILL, (p.returncode, p.stderr[-2000:])
    assert not out.exists() or fault == "finalize.aside"
    summary = _run(synth_world, out)  # the same command, no fault
    assert summary.store_written
    if fault.startswith("cache"):
        assert 0 < sum(summary.cached_shards.values()) < len(STAGES) * summary.n_shards
    else:
        assert sum(summary.computed_shards.values()) == 0  # everything came from the cache
    assert_same_store(out, reference[0])


def test_sigkill_while_replacing_an_older_store(synth_world, reference, tmp_path):
    out = tmp_path / "s.zarr"
    _run(synth_world, out, ["stages.view.params.mean_error_deg=30"])  # an older store at --out
    p = _cli_run(synth_world, out, "finalize.aside:1")
    assert p.returncode == -signal.SIGKILL, p.stderr[-2000:]
    _run(synth_world, out)
    assert_same_store(out, reference[0])


def test_changing_one_parameter_recomputes_only_that_stage_and_its_dependents(synth_world, reference, tmp_path):
    out = tmp_path / "s.zarr"
    work = tmp_path / "work"
    first = _run(synth_world, out, work_dir=work)
    assert all(first.computed_shards[s] == 4 for s in STAGES)
    again = _run(synth_world, out, work_dir=work)
    assert sum(again.computed_shards.values()) == 0
    assert not again.store_written

    v30 = _run(synth_world, out, ["stages.view.params.mean_error_deg=30"], work_dir=work)
    assert {s: v30.computed_shards[s] for s in STAGES} == {
        "input": 0, "depth": 0, "objects": 0, "head": 0, "pose": 0, "view": 4}
    a, b = open_store(reference[0]), open_store(out)
    np.testing.assert_array_equal(a.frames["pose"], b.frames["pose"])
    np.testing.assert_array_equal(a.objects["xyz"], b.objects["xyz"])
    assert not np.array_equal(a.frames["view"], b.frames["view"])

    head = _run(synth_world, out, ["stages.view.params.mean_error_deg=30", "stages.head.params.min_points=5"],
                work_dir=work)
    assert {s for s in STAGES if head.computed_shards[s]} == {"head"}

    dep = _run(synth_world, out, ["stages.view.params.mean_error_deg=30", "stages.head.params.min_points=5",
                                  "stages.depth.params.blur=none"], work_dir=work)
    assert {s for s in STAGES if dep.computed_shards[s]} == {"depth", "objects", "head"}


def test_a_second_run_on_the_same_output_is_refused(synth_world, tmp_path):
    out = tmp_path / "s.zarr"
    with RunLock(Path(str(out) + ".work"), str(out)):
        with pytest.raises(StoreError, match="another ga3ce-prep run is writing"):
            _run(synth_world, out)
    _run(synth_world, out)  # released: runs


def test_shard_size_and_workers_do_not_change_the_store(synth_world, reference, tmp_path):
    out = tmp_path / "s.zarr"
    run_pipeline(PIPE, synth_world, out, overrides=[*SMALL, "run.shard_size=5"], workers=2, progress=False)
    assert_same_store(out, reference[0], attrs=False)
    assert open_store(out).attrs["run"]["n_shards"] == 3


def _corrupt(src: Path, dst: Path) -> dict[str, str]:
    """Copy the world and break one frame per bad-input class; returns frame id -> class."""
    shutil.copytree(src, dst)
    ids = [f"train/scene1/{k:04d}" for k in range(4)] + [f"valid/scene1/{k:04d}" for k in range(2)]
    broken = dict(zip(ids, ["missing_image", "truncated_image", "missing_depth", "invalid_head_depth",
                            "box_outside", "ok"]))
    rgb, dep = dst / "rgb", dst / "depth"
    (rgb / "train/scene1/0000.jpg").unlink()
    data = (rgb / "train/scene1/0001.jpg").read_bytes()
    (rgb / "train/scene1/0001.jpg").write_bytes(data[: len(data) // 3])
    (dep / "train/scene1/0002.npy").unlink()
    ann = list(csv.reader(open(dst / "train_annotation.txt")))
    header = ann[0]
    col = {c: header.index(c) for c in header}
    row3 = next(r for r in ann[1:] if int(r[col["frame_id"]]) == 3 and int(r[col["scene_id"]]) == 1)
    d = np.load(dep / "train/scene1/0003.npy")
    x1, y1, x2, y2 = (float(row3[col[c]]) for c in ("h_x_min", "h_y_min", "h_x_max", "h_y_max"))
    w, h = x2 - x1, y2 - y1
    d[max(0, int(y1 - h)):int(y2 + h) + 1, max(0, int(x1 - w)):int(x2 + w) + 1] = np.nan
    np.save(dep / "train/scene1/0003.npy", d)
    vann = list(csv.reader(open(dst / "valid_annotation.txt")))
    vcol = {c: vann[0].index(c) for c in vann[0]}
    row = next(r for r in vann[1:] if int(r[vcol["frame_id"]]) == 0 and int(r[vcol["scene_id"]]) == 1)
    row[vcol["h_x_min"]], row[vcol["h_x_max"]] = "400", "420"  # the image is 160 wide
    with open(dst / "valid_annotation.txt", "w", newline="") as f:
        csv.writer(f).writerows(vann)
    return broken


EXPECT = {  # bad-input class -> (stage, error class, message fragment)
    "missing_image": ("input", "FrameError", "image file not found"),
    "truncated_image": ("input", "FrameError", "cannot decode image"),
    "missing_depth": ("depth", "FrameError", "depth file not found"),
    "box_outside": ("head", "FrameError", "lies outside the 160x120 image"),
}


def test_bad_inputs_become_failure_records_and_other_frames_are_intact(synth_world, reference, tmp_path):
    data = tmp_path / "bad"
    broken = _corrupt(synth_world, data)
    summary = _run(data, tmp_path / "s.zarr")
    s, ref = open_store(tmp_path / "s.zarr"), open_store(reference[0])
    assert summary.counts.frames_kept == 12 - 4
    assert summary.counts.frames_dropped == 4
    f = s.failures
    got = {fid: (st, err, msg, act) for fid, st, err, msg, act in
           zip(f["frame_id"], f["stage"], f["error"], f["message"], f["action"])}
    assert len(f["frame_id"]) == 4
    head_source = dict(zip(s.frames["id"], np.asarray(s.source_names["head"])[s.frames["head_source"]]))
    for fid, kind in broken.items():
        if kind in ("ok", "invalid_head_depth"):  # no measured depth near the head: the pose's head
            assert fid not in got
            assert head_source[fid] == ("measured" if kind == "ok" else "pose_depth")
            continue
        stage, err, frag = EXPECT[kind]
        assert got[fid][:2] == (stage, err), (fid, got[fid])
        assert frag in got[fid][2], got[fid][2]
        assert got[fid][3] == "dropped"
        assert fid not in s.frames["id"]
    assert summary.counts.dropped_by_stage == {"input": 2, "depth": 1, "head": 1}
    # the other frames are exactly as in the clean run
    keep = np.isin(ref.frames["id"], s.frames["id"]) & (ref.frames["id"] != "train/scene1/0003")
    s.frames = {k: v[s.frames["id"] != "train/scene1/0003"] for k, v in s.frames.items()}
    s.objects["xyz"] = np.concatenate([s.objects_of(i) for i in range(len(s))])
    for name in ("head_pos", "pose", "view", "obj_count", "K", "gaze"):
        np.testing.assert_array_equal(s.frames[name], ref.frames[name][keep], err_msg=name)
    ref_objs = np.concatenate([ref.objects_of(i) for i in np.flatnonzero(keep)])
    np.testing.assert_array_equal(s.objects["xyz"], ref_objs)


def test_turning_on_cache_depth_maps_keeps_the_depth_failure_records(synth_world, tmp_path):
    data = tmp_path / "bad"
    _corrupt(synth_world, data)
    work = tmp_path / "work"
    _run(data, tmp_path / "a.zarr", work_dir=work, shard_size=4)
    maps = _run(data, tmp_path / "b.zarr", ["run.cache_depth_maps=true", "stages.objects.params.max_planes=3"],
                work_dir=work, shard_size=4)
    assert {s for s in STAGES if maps.computed_shards[s]} == {"depth", "objects"}  # depth again, to keep its maps
    a, b = open_store(tmp_path / "a.zarr"), open_store(tmp_path / "b.zarr")
    np.testing.assert_array_equal(a.frames["id"], b.frames["id"])
    for name in a.failures:
        np.testing.assert_array_equal(a.failures[name], b.failures[name], err_msg=name)


def test_nan_intrinsics_stop_the_run_before_any_work(synth_world, tmp_path):
    data = tmp_path / "nank"
    shutil.copytree(synth_world, data)
    np.save(data / "CameraKinect.npy", np.array([np.nan, 140.0, 80.0, 60.0]))
    with pytest.raises(DatasetFormatError, match=r"CameraKinect.npy: intrinsics fx nan, fy 140.*not finite"):
        _run(data, tmp_path / "s.zarr", ["run.shard_size=12"])
    assert not (tmp_path / "s.zarr").exists()
    assert not (tmp_path / "s.zarr.work").exists()


def test_failed_pose_or_objects_degrade_the_frame_instead_of_dropping_it():
    from ga3ce_prep.frames import FrameRef

    frames = [FrameRef(id=f"f{i}", split="test", scene="s", image_path=Path("x"), K=np.eye(3), image_size=(4, 3),
                       head_box=np.zeros(4, np.float32)) for i in range(2)]
    shard = Shard(0, frames)
    none = {"fail_idx": np.zeros(0, np.int64), "fail_error": np.zeros(0, str), "fail_message": np.zeros(0, str)}
    ok = np.ones(2, bool)
    e = {st: {"ids": shard.ids, "ok": ok, **none} for st in STAGES}
    e["objects"].update(ok=np.array([True, False]), count=np.array([2, 0]), n_dropped=np.zeros(2),
                        xyz=np.ones((2, 3), np.float32), area=np.ones(2, np.int32), score=np.ones(2, np.float32),
                        fail_idx=np.array([1]), fail_error=np.array(["RuntimeError"]), fail_message=np.array(["boom"]))
    e["pose"].update(ok=np.array([False, True]), pose=np.zeros((2, 30, 3), np.float32), fail_idx=np.array([0]),
                     fail_error=np.array(["FrameError"]), fail_message=np.array(["no pose"]))
    e["head"]["head_pos"] = np.zeros((2, 3), np.float32)
    e["view"]["view"] = np.tile(np.float32([0, 0, 1]), (2, 1))
    c = FinalizeCounts()
    fr, obj, fails = shard_block(shard, e, c)
    assert fr["id"].tolist() == ["f0", "f1"]                      # both kept
    assert fr["obj_count"].tolist() == [2, 0]
    assert len(obj["xyz"]) == 2
    assert np.isnan(fr["pose"][0]).all()
    assert (fr["pose"][1] == 0).all()
    assert sorted((r[1], r[4]) for r in fails) == [("objects", "degraded"), ("pose", "degraded")]
    assert c.degraded_by_stage == {"objects": 1, "pose": 1}
    assert not c.dropped_by_stage


def test_info_show_export_commands(synth_world, reference, tmp_path):
    out = reference[0]
    r = CliRunner()
    res = r.invoke(cli, ["info", str(out)])
    assert res.exit_code == 0, res.output
    assert "frames       12" in res.output
    assert "splits" in res.output
    assert "[ORACLE" in res.output
    assert "synthetic    unseen-rooms: one session per room, split by room (3 rooms, seed 5)" in res.output
    fid = open_store(out).frames["id"][0]
    png = tmp_path / "f.png"
    res = r.invoke(cli, ["show", str(out), fid, "--out", str(png)])
    assert res.exit_code == 0, res.output
    import cv2

    img = cv2.imread(str(png))
    assert img is not None
    assert min(img.shape[:2]) >= 480
    ply = tmp_path / "f.ply"
    res = r.invoke(cli, ["show", str(out), fid, "--out", str(ply)])
    assert res.exit_code == 0, res.output
    import open3d as o3d

    pc = o3d.io.read_point_cloud(str(ply))
    assert len(pc.points) > 160 * 120 * 0.5  # the frame's depth points plus the context
    h5 = tmp_path / "s.h5"
    res = r.invoke(cli, ["export", str(out), "--format", "hdf5", str(h5)])
    assert res.exit_code == 0, res.output
    s = open_store(out)
    with h5py.File(h5, "r") as f:
        for group in ("frames", "objects", "failures"):
            for name, a in getattr(s, group).items():
                b = f[group][name].asstr()[...] if a.dtype.kind in "UOT" else f[group][name][...]
                np.testing.assert_array_equal(np.asarray(b), a, err_msg=f"{group}/{name}")
        assert f["frames/scene"].attrs["names"].startswith("[")
    res = r.invoke(cli, ["show", str(out), "no/such/frame", "--out", str(png)])
    assert res.exit_code != 0
    assert "not in" in str(res.exception)


def _tree(root: Path) -> dict[str, bytes]:
    """Every file under root, by relative path, with its bytes."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_a_foreign_zarr_store_at_out_is_refused_untouched_and_replaced_only_with_overwrite(synth_world, reference,
                                                                                          tmp_path):
    out = tmp_path / "theirs.zarr"
    g = zarr.open_group(str(out), mode="w")
    g.attrs["owner"] = "another project"
    g.create_array("x", data=np.arange(10))
    before = _tree(out)
    with pytest.raises(StoreError, match=r"holds a Zarr store that ga3ce-prep did not write \(root attributes: owner;"
                                         r".*to replace it pass --overwrite, to keep it choose another --out"):
        _run(synth_world, out)
    assert _tree(out) == before
    assert not Path(f"{out}.work").exists() and not Path(f"{out}.lock").exists()  # refused before anything

    args = ["run", "-p", PIPE, "-d", str(synth_world), "-o", str(out), "-q", "--overwrite"]
    res = CliRunner().invoke(cli, args + [a for o in (*SMALL, *SHARD) for a in ("--set", o)])
    assert res.exit_code == 0, res.output
    assert not (out / "x").exists()
    assert_same_store(out, reference[0])

    mine = tmp_path / "notes"  # not a Zarr store: refused even with --overwrite
    mine.mkdir()
    (mine / "a.txt").write_text("mine")
    with pytest.raises(StoreError, match="exists and is not a Zarr store"):
        _run(synth_world, mine, overwrite=True)
    assert _tree(mine) == {"a.txt": b"mine"}


def test_a_store_of_another_pipeline_or_dataset_is_refused_untouched_unless_overwrite(synth_world, reference, tmp_path):
    other = tmp_path / "world2"
    shutil.copytree(synth_world, other)
    out = tmp_path / "s.zarr"
    shutil.copytree(reference[0], out)  # pipeline synthetic on synth_world
    before = _tree(out)
    theirs = f"the ga3ce-prep store of pipeline 'synthetic' on the gfie dataset at {synth_world} (12 frames, schema "
    with pytest.raises(StoreError, match=re.escape(theirs) + r".*not this run's pipeline 'synthetic' on the gfie "
                                         rf"dataset at {re.escape(str(other))}; to replace it pass --overwrite"):
        _run(other, out)
    with pytest.raises(StoreError, match=re.escape(theirs) + r".*not this run's pipeline 'synthetic-oracle'"):
        run_pipeline("synthetic-oracle", synth_world, out, overrides=SHARD, progress=False)
    assert _tree(out) == before
    _run(synth_world, out)  # the same pipeline and dataset: ours to replace (here: already up to date)
    assert _tree(out) == before
    summary = _run(other, out, overwrite=True)
    assert summary.store_written
    assert open_store(out, verify=True).attrs["dataset"]["root"] == str(other)


def test_two_runs_on_one_output_with_different_work_directories_the_second_is_refused(synth_world, tmp_path):
    out, work1 = tmp_path / "s.zarr", tmp_path / "work1"
    first = subprocess.Popen([sys.executable, "-c", "import sys; from ga3ce_prep.pipeline.lock import RunLock\n"
                              f"with RunLock({str(work1)!r}, {str(out)!r}):\n"
                              " print('held', flush=True); sys.stdin.read()"],
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert first.stdout.readline().strip() == "held"
        with pytest.raises(StoreError, match=rf"another ga3ce-prep run is writing {re.escape(str(out))} \(pid "
                                             rf"{first.pid} on .*, work directory {re.escape(str(work1))}, "
                                             rf"started .*\) and holds {re.escape(str(out))}.lock"):
            _run(synth_world, out, work_dir=tmp_path / "work2")
        assert not out.exists() and not (tmp_path / "work2" / "cache").exists()
    finally:
        first.communicate("", timeout=60)
    _run(synth_world, out, work_dir=tmp_path / "work2")  # released: runs
    assert open_store(out, verify=True)


def _flip_data_bit(entry: Path) -> None:
    """Flip a bit in the last data byte of the largest array of an .npz cache entry."""
    with zipfile.ZipFile(entry) as z:
        info = max(z.infolist(), key=lambda i: i.file_size)
    raw = bytearray(entry.read_bytes())
    name_len, extra_len = struct.unpack("<HH", raw[info.header_offset + 26:info.header_offset + 30])
    at = info.header_offset + 30 + name_len + extra_len + info.compress_size - 1
    raw[at] ^= 0x01
    entry.write_bytes(bytes(raw))


@pytest.mark.parametrize("damage", ["flipped bit", "truncated"])
def test_damaged_cache_entries_are_recomputed_in_the_same_rerun(synth_world, reference, tmp_path, damage, caplog):
    out, work = tmp_path / "s.zarr", tmp_path / "work"
    _run(synth_world, out, work_dir=work)
    shutil.rmtree(out)  # so that the rerun must finalize from the cache
    cache = work / "cache"
    spoil = _flip_data_bit if damage == "flipped bit" else lambda p: p.write_bytes(p.read_bytes()[:200])
    for entry in (cache / "input").glob("*/*.npz"):  # read by the view tasks below
        spoil(entry)
    for entry in (cache / "view").glob("*/*.npz"):   # so the view tasks run
        entry.unlink()
    spoil(sorted((cache / "objects").glob("*/*.npz"))[0])  # read by finalize only
    summary = _run(synth_world, out, work_dir=work)
    assert summary.store_written
    assert {s: summary.computed_shards[s] for s in STAGES} == {
        "input": 4, "depth": 0, "objects": 1, "head": 0, "pose": 0, "view": 4}
    assert_same_store(out, reference[0])
    assert sum("is damaged" in r.getMessage() for r in caplog.records) == 5


def test_a_crc_consistent_edit_of_a_cache_entry_is_recomputed(synth_world, reference, tmp_path, caplog):
    from ga3ce_prep.pipeline.cache import DIGEST, content_digest

    out, work = tmp_path / "s.zarr", tmp_path / "work"
    _run(synth_world, out, work_dir=work)
    entry = sorted((work / "cache" / "view").glob("*/*.npz"))[1]
    z = dict(np.load(entry))
    recorded = str(z.pop(DIGEST))
    np.savez(entry, **z)                                   # an entry from before the digest: read as before
    shutil.rmtree(out)
    summary = _run(synth_world, out, work_dir=work)
    assert summary.store_written and sum(summary.computed_shards.values()) == 0
    assert_same_store(out, reference[0])
    z["view"] = z["view"][::-1].copy()                     # an edit, its CRC-32 recomputed by np.savez
    np.savez(entry, **z, **{DIGEST: np.array(recorded)})
    with zipfile.ZipFile(entry) as zf:
        assert zf.testzip() is None
    shutil.rmtree(out)
    summary = _run(synth_world, out, work_dir=work)
    assert summary.store_written
    assert {s: summary.computed_shards[s] for s in STAGES} == {
        "input": 0, "depth": 0, "objects": 0, "head": 0, "pose": 0, "view": 1}
    assert_same_store(out, reference[0])
    assert [r.getMessage() for r in caplog.records if "is damaged" in r.getMessage()] == [
        f"cache entry {entry} is damaged (EntryChanged: its arrays differ from their SHA-256 recorded in "
        f"{DIGEST} (changed after it was written; its CRC-32 matches)): removed, it is computed again"]
    again = dict(np.load(entry))                           # computed again, with its own digest
    np.testing.assert_array_equal(again["view"], z["view"][::-1])
    assert str(again.pop(DIGEST)) == content_digest(again)


def test_cache_entries_carry_their_digest_apart_from_their_arrays(tmp_path):
    from ga3ce_prep.pipeline.cache import DIGEST, Cache, content_digest

    cache = Cache(tmp_path / "cache")
    arrays = {"ids": np.array(["a", "b"]), "ok": np.array([True, False]), "fail_idx": np.array([1]),
              "fail_error": np.array(["FrameError"]), "fail_message": np.array(["no depth"]),
              "view": np.ones((2, 3), np.float32), "seconds": np.float64(0.5)}
    path = cache.save("view", "ab" * 32, arrays)
    assert str(np.load(path)[DIGEST]) == content_digest(arrays)
    got = cache.load("view", "ab" * 32)
    assert sorted(got) == sorted(arrays)
    for k in arrays:
        np.testing.assert_array_equal(got[k], arrays[k])
    with pytest.raises(ValueError, match=DIGEST):
        cache.save("view", "cd" * 32, {**arrays, DIGEST: np.array("x")})


def test_a_rerun_repairs_a_damaged_store(synth_world, reference, tmp_path):
    out = tmp_path / "s.zarr"
    _run(synth_world, out)
    (out / "frames/pose/c/0/0/0").unlink()
    with pytest.raises(StoreError, match=r"array frames/pose, chunk \(0, 0, 0\) \(rows 0-11\): missing"):
        open_store(out, verify=True)
    summary = _run(synth_world, out)
    assert summary.store_written
    assert sum(summary.computed_shards.values()) == 0
    assert_same_store(out, reference[0])
