"""`ga3ce-prep view` (ga3ce_prep/view.py): a recording of a small synthetic store, read back with Rerun's
own reader (rerun.chunk.RrdReader), checked entity by entity and frame by frame against the store, the
dataset's files and the checkpoint; the store read a block at a time; the extra's absence; and the web
viewer loaded in headless chromium (ga3ce_prep/testing/browser.py)."""
import re
import signal
import subprocess
import sys
import tomllib
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from click.testing import CliRunner

from ga3ce_prep import view as view_module
from ga3ce_prep.cli import cli
from ga3ce_prep.errors import ConfigError, Ga3ceError
from ga3ce_prep.frames import load_rgb
from ga3ce_prep.geometry import angular_error_deg, depth_to_points, normalize, object_positions
from ga3ce_prep.model import ModelConfig
from ga3ce_prep.pipeline import run_pipeline
from ga3ce_prep.skeleton import BONES
from ga3ce_prep.store import INDEX_ARRAYS, open_lazy, open_store
from ga3ce_prep.testing.cluster import free_port
from ga3ce_prep.testing.recordings import read_recording
from ga3ce_prep.testing.worlds import SMALL
from ga3ce_prep.train import ContextDataset, TrainConfig, predict, train
from ga3ce_prep.train.checkpoint import build_model, load_checkpoint
from ga3ce_prep.view import (
    ARROW_M,
    BLOCK,
    INSTALL,
    StoreStages,
    bone_segments,
    cloud,
    depth_step,
    grid_step,
    mask_labels,
    object_radii,
    select_rows,
    session_positions,
)
from ga3ce_prep.viz import find_frame_refs

torch.set_num_threads(2)
BUDGET = 500  # points per frame: below the 160x120 frames' 19,200 pixels, so the grid thins them


@pytest.fixture(scope="module")
def store(synth_world, tmp_path_factory):
    """The 160x120 synthetic world (3 sessions x 4 frames) through the demo's pipeline, and a small model
    trained one epoch on it."""
    root = tmp_path_factory.mktemp("view")
    out = root / "s.zarr"
    run_pipeline("synthetic", synth_world, out, overrides=SMALL, progress=False)
    small = ModelConfig(num_encoder_layers=1, num_decoder_layers=1, dim_feedforward=128, head_hidden=128)
    run = train(TrainConfig(store=str(out), out=str(root / "run"), epochs=1, batch_size=4, warmup_epochs=0,
                            progress=False, model=small))
    return out, run / "best.pt"


@pytest.fixture(scope="module")
def recorded(store, tmp_path_factory):
    """The whole store, with the checkpoint and the masks, as `ga3ce-prep view` records it."""
    path, ckpt = store
    rrd = tmp_path_factory.mktemp("rrd") / "all.rrd"
    res = CliRunner().invoke(cli, ["view", str(path), "-c", str(ckpt), "--masks", "--points", str(BUDGET),
                                   "--save", str(rrd)], catch_exceptions=False)
    assert res.exit_code == 0, res.output
    return rrd, res.output, read_recording(rrd)


def _png(row, key):
    return cv2.imdecode(np.frombuffer(bytes(row[key][0]), np.uint8), cv2.IMREAD_UNCHANGED)


def _arrow(row):
    return np.array(row["Arrows3D:origins"][0]), np.array(row["Arrows3D:vectors"][0])


def test_the_recording_holds_every_frame_of_the_store_as_the_store_has_it(store, recorded):
    path, ckpt = store
    rrd, output, rec = recorded
    s = open_store(path)
    n = len(s)
    assert re.search(rf"\b{n} frames of 3 session\(s\): image {n}, depth {n}, masks {n}", output), output
    # the axes: the store's camera frame, x right, y down, z forward (Rerun's RDF)
    import rerun as rr

    rdf = [int(d) for d in rr.ViewCoordinates.RDF.as_arrow_array().to_pylist()[0]]
    assert rec.static("/")[0]["ViewCoordinates:xyz"] == [rdf]
    # a timeline per session (its frames numbered 0, 1, ... in store order), and `row`
    assert rec.timelines() == {"row", *s.scene_names}
    ids = rec.at("/frames/id", "row")
    assert sorted(ids) == list(range(n))
    refs = find_frame_refs(s, s.frames["id"].tolist())
    stages = StoreStages(s.attrs, Path(s.attrs["dataset"]["root"]), masks=True)
    ds = ContextDataset(s, require_gaze=False)
    g = predict(build_model(load_checkpoint(ckpt)), ds)    # the model's g as `eval` computes it, whole store
    assert len(ds) == n
    for i in range(n):
        fid = str(s.frames["id"][i])
        session = s.scene_names[int(s.frames["scene"][i])]
        assert ids[i]["TextDocument:text"] == [fid]
        assert ids[i][session] == int(np.sum(s.frames["scene"][:i] == s.frames["scene"][i]))
        at = {e: rec.at(e, "row").get(i) for e in rec.rows}
        K = s.frames["K"][i]
        np.testing.assert_allclose(np.array(at["/camera"]["Pinhole:image_from_camera"][0]).reshape(3, 3).T, K)
        assert at["/camera"]["Pinhole:resolution"] == [s.frames["image_size"][i].astype(float).tolist()]
        c, h = np.array(at["/camera/frames/head_box"]["Boxes2D:centers"][0]), \
            np.array(at["/camera/frames/head_box"]["Boxes2D:half_sizes"][0])
        np.testing.assert_allclose(np.r_[c - h, c + h], s.frames["head_box"][i], atol=1e-4)
        # the objects: positions, index labels, radii from the mask areas
        xyz = s.objects_of(i)
        np.testing.assert_array_equal(np.array(at["/objects/xyz"]["Points3D:positions"], np.float32), xyz)
        assert at["/objects/xyz"]["Points3D:labels"] == [str(k) for k in range(len(xyz))]
        np.testing.assert_allclose(at["/objects/xyz"]["Points3D:radii"],
                                   object_radii(xyz, s.objects["area"][s.object_slice(i)], K), rtol=1e-6)
        head = s.frames["head_pos"][i]
        np.testing.assert_array_equal(np.array(at["/frames/head_pos"]["Points3D:positions"][0], np.float32), head)
        pose = s.frames["pose"][i]
        joints = np.flatnonzero(np.isfinite(pose).all(1))
        assert at["/frames/pose"]["Points3D:keypoint_ids"] == joints.tolist()
        np.testing.assert_array_equal(np.array(at["/frames/pose"]["Points3D:positions"], np.float32), pose[joints])
        bones = np.array(at["/frames/pose/bones"]["LineStrips3D:strips"], np.float32)
        assert bones.shape == (len(BONES), 2, 3)              # every joint is there: every bone
        np.testing.assert_array_equal(bones, bone_segments(pose))
        # the arrows: from t_object, ARROW_M long, along v, the truth's gaze and the model's g
        for entity, d in (("/frames/view", s.frames["view"][i]), ("/frames/gaze", s.frames["gaze"][i]),
                          ("/model/gaze", g[i])):
            origin, vector = _arrow(at[entity])
            np.testing.assert_allclose(origin, head, atol=1e-6)
            np.testing.assert_allclose(vector, ARROW_M * normalize(d.astype(np.float64)), atol=1e-5)
        np.testing.assert_allclose(at["/error_deg/model"]["Scalars:scalars"][0],
                                   angular_error_deg(g[i], s.frames["gaze"][i]), atol=1e-3)
        np.testing.assert_allclose(at["/error_deg/view"]["Scalars:scalars"][0],
                                   angular_error_deg(s.frames["view"][i], s.frames["gaze"][i]), atol=1e-4)
        # the image: the dataset's, through JPEG
        rgb = load_rgb(refs[fid].image_path)
        jpg = _png(at["/camera/image"], "EncodedImage:blob")[..., ::-1]
        assert jpg.shape == rgb.shape and np.abs(jpg.astype(int) - rgb).mean() < 4
        # the completed depth, as the store's depth backend makes it: in mm, every step-th pixel
        dm = stages.depth(refs[fid])
        step = depth_step(dm.depth.shape)
        assert at["/depth/image"]["EncodedDepthImage:meter"] == [1000.0]
        np.testing.assert_array_equal(_png(at["/depth/image"], "EncodedDepthImage:blob"),
                                      np.round(dm.depth[::step, ::step] * np.float32(1000)).astype(np.uint16))
        # the points: the depth back-projected on the budget's grid, coloured by the image
        s_ = grid_step(dm.depth.shape, BUDGET)
        ok = dm.depth[::s_, ::s_] > 0
        pts = np.array(at["/depth/points"]["Points3D:positions"], np.float32)
        assert len(pts) == ok.sum() <= BUDGET
        np.testing.assert_array_equal(pts, depth_to_points(dm.depth, K)[::s_, ::s_][ok])
        colours = np.array(at["/depth/points"]["Points3D:colors"], np.uint32)
        np.testing.assert_array_equal(np.stack([colours >> 24, (colours >> 16) & 255, (colours >> 8) & 255], 1),
                                      rgb[::s_, ::s_][ok])
        # the masks: object k is label k + 1, and its measured pixels' median is the store's position
        buf = at["/camera/masks"]
        labels = np.frombuffer(bytes(buf["SegmentationImage:buffer"][0]), np.uint16).reshape(dm.depth.shape)
        again = object_positions(dm.depth, K, labels.astype(np.int64) - 1, dm.valid, min_points=1)
        np.testing.assert_array_equal(again.index, np.arange(len(xyz)))
        np.testing.assert_allclose(again.xyz, xyz, atol=1e-6)
    most = int(s.frames["obj_count"].max())
    classes = rec.static("/camera/masks")[0]["AnnotationContext:context"][0]
    assert [(c["class_id"], c["class_description"]["info"]["label"]) for c in classes] == \
        [(k + 1, str(k)) for k in range(most)]


def test_a_frame_without_a_value_clears_the_last_one(store, tmp_path):
    """The viewer shows the latest value at a time: a NaN gaze, a missing image or depth is a Clear."""
    import rerun as rr

    path, _ = store
    block = open_lazy(path).rows(np.array([0, 1]))
    block.frames["gaze"][1] = np.nan
    block.frames["pose"][1] = np.nan
    sink = view_module.Sink(save=tmp_path / "c.rrd")
    rr_, rec, url = sink.open("clears")
    for k in range(2):
        fv = view_module.frame_view(block, k, rgb=np.zeros((120, 160, 3), np.uint8) if k == 0 else None,
                                    depth=np.ones((120, 160), np.float32) if k == 0 else None,
                                    masks=np.ones((120, 160), np.uint16) if k == 0 else None)
        view_module.log_frame(rr, rec, fv, {"row": k}, masks=True)
    sink.close(rec, url)
    r = read_recording(tmp_path / "c.rrd")
    for entity in ("/frames/gaze", "/frames/pose", "/frames/pose/bones", "/camera/image", "/depth/image",
                   "/depth/points", "/camera/masks"):
        first, second = r.at(entity, "row")[0], r.at(entity, "row")[1]
        assert "Clear:is_recursive" not in first and second["Clear:is_recursive"] == [False], entity
    assert 1 not in r.at("/error_deg/view", "row")           # no truth: no error point


def test_choosing_frames_by_session_split_and_id(store, tmp_path):
    path, _ = store
    s = open_lazy(path)
    scene, split = s.index["scene"], s.index["split"]
    one = s.scene_names[1]
    np.testing.assert_array_equal(select_rows(s, sessions=(one,)), np.flatnonzero(scene == 1))
    test = np.flatnonzero(split == s.split_names.index("test"))
    np.testing.assert_array_equal(select_rows(s, splits=("test",)), test)
    ids = [str(x) for x in s.index["id"][[2, 7]].tolist()]
    np.testing.assert_array_equal(select_rows(s, frames=tuple(ids)), [2, 7])
    np.testing.assert_array_equal(select_rows(s), np.arange(len(s)))
    with pytest.raises(ConfigError, match="no session 'nowhere'.*its sessions: " + re.escape(s.scene_names[0])):
        select_rows(s, sessions=("nowhere",))
    with pytest.raises(ConfigError, match="no frame is in all"):
        select_rows(s, sessions=(one,), frames=(ids[1],) if scene[7] != 1 else (ids[0],))
    np.testing.assert_array_equal(session_positions(np.array([2, 0, 2, 0, 1, 2])), [0, 0, 1, 1, 0, 2])
    # the command: one session, on its timeline only
    rrd = tmp_path / "one.rrd"
    res = CliRunner().invoke(cli, ["view", str(path), "--session", one, "--no-depth", "--save", str(rrd)])
    assert res.exit_code == 0, res.output
    rec = read_recording(rrd, blobs=False)
    assert rec.timelines() == {"row", one}
    assert sorted(rec.at("/frames/id", one)) == list(range(int((scene == 1).sum())))
    assert "/depth/points" in rec.rows and all("Clear:is_recursive" in r for r in rec.rows["/depth/points"])
    assert "/camera/masks" not in rec.rows and "/model/gaze" not in rec.rows     # not asked for: not there


def test_the_store_streams_a_block_at_a_time(store, tmp_path, monkeypatch):
    """open_lazy holds the index columns only; `view` reads the store BLOCK rows at a time, and the
    recording is the same whatever the block."""
    path, _ = store
    lazy, whole = open_lazy(path), open_store(path)
    assert set(lazy.index) == set(INDEX_ARRAYS)
    rows = np.array([9, 0, 4, 11])
    part = lazy.rows(rows)
    for name, a in whole.frames.items():
        if name != "obj_start":
            np.testing.assert_array_equal(part.frames[name], a[rows])
    for k, r in enumerate(rows):
        np.testing.assert_array_equal(part.objects_of(k), whole.objects_of(r))
        np.testing.assert_array_equal(part.objects["area"][part.object_slice(k)],
                                      whole.objects["area"][whole.object_slice(r)])
    asked = []
    rows_of = type(lazy).rows

    def spy(self, r):
        asked.append(len(r))
        return rows_of(self, r)

    monkeypatch.setattr(type(lazy), "rows", spy)
    monkeypatch.setattr(view_module, "BLOCK", 5)
    res = CliRunner().invoke(cli, ["view", str(path), "--no-depth", "--save", str(tmp_path / "b.rrd")])
    assert res.exit_code == 0, res.output
    assert asked == [5, 5, 2] and BLOCK > 5
    monkeypatch.undo()
    CliRunner().invoke(cli, ["view", str(path), "--no-depth", "--save", str(tmp_path / "a.rrd")])
    a, b = read_recording(tmp_path / "a.rrd"), read_recording(tmp_path / "b.rrd")
    for entity in ("/objects/xyz", "/frames/pose", "/frames/view", "/frames/id"):
        assert [{k: v for k, v in r.items()} for r in a.rows[entity]] == b.rows[entity], entity


def test_the_parts_of_a_frame():
    assert grid_step((120, 160), 500) == 7                   # 18 x 23 = 414 pixels; at step 6, 20 x 27 = 540
    depth = np.zeros((4, 6), np.float32)
    depth[0, 0], depth[2, 4] = 2.0, 3.0
    K = np.array([[10.0, 0, 3], [0, 10.0, 2], [0, 0, 1]])
    rgb = np.arange(4 * 6 * 3, dtype=np.uint8).reshape(4, 6, 3)
    pts, cols = cloud(depth, K, rgb, budget=6)                 # step 2: pixels (0, 0) and (2, 4) with depth
    np.testing.assert_allclose(pts, [[-0.6, -0.4, 2.0], [0.3, 0.0, 3.0]])
    np.testing.assert_array_equal(cols, rgb[[0, 2], [0, 4]])
    assert (cloud(depth, K, None, 6)[1] == 150).all()
    # radius: 0.3 of the extent of a disc of the mask's area at its depth, clipped to 2-15 cm
    wide = np.diag([1000.0, 1000.0, 1.0])                        # a disc of radius 150 px at 2 m: 0.3 m across
    r = object_radii(np.array([[0, 0, 2.0], [0, 0, 2.0], [0, 0, 9.0]]), np.array([150**2 * np.pi, 1, 10**6]), wide)
    np.testing.assert_allclose(r, [0.3 * 150 * 2 / 1000, 0.02, 0.15], rtol=1e-6)
    pose = np.zeros((30, 3), np.float32)
    pose[BONES[0][0]] = np.nan
    assert len(bone_segments(pose)) == len(BONES) - sum(1 for j, p in BONES if BONES[0][0] in (j, p))
    # masks: a label image (negative none), and a stack drawn largest first
    lab = np.array([[3, 3, -1], [5, 5, 5]])
    np.testing.assert_array_equal(mask_labels(lab, np.array([5, 3]), lab.shape), [[2, 2, 0], [1, 1, 1]])
    stack = np.zeros((3, 2, 3), bool)
    stack[0] = True
    stack[2, 0, 0] = True
    np.testing.assert_array_equal(mask_labels(stack, np.array([0, 2]), (2, 3)), [[2, 1, 1], [1, 1, 1]])


def test_without_the_extra_the_command_says_how_to_add_it(store, monkeypatch, tmp_path):
    path, _ = store
    monkeypatch.setitem(sys.modules, "rerun", None)          # `import rerun` raises ImportError
    with pytest.raises(Ga3ceError, match=re.escape(INSTALL)):
        view_module.import_rerun()
    res = subprocess.run([sys.executable, "-c", "import sys; sys.modules['rerun'] = None; from ga3ce_prep.cli import "
                          f"main; sys.argv = ['ga3ce-prep', 'view', {str(path)!r}, '--save', 'x.rrd']; main()"],
                         capture_output=True, text=True, cwd=tmp_path)
    assert res.returncode == 2 and INSTALL in res.stderr, res.stderr
    # the base install lacks it: importing the command's module imports no rerun
    res = subprocess.run([sys.executable, "-c", "import sys, ga3ce_prep.view, ga3ce_prep.predict; "
                          "print('rerun' in sys.modules)"], capture_output=True, text=True, check=True)
    assert res.stdout.strip() == "False" and not (tmp_path / "x.rrd").exists()
    project = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())["project"]
    assert not [d for d in project["dependencies"] if d.startswith(("rerun", "pyarrow"))]
    assert project["optional-dependencies"]["view"] == ["rerun-sdk>=0.41,<0.42"]


def test_a_sink_is_one_of_save_spawn_serve(tmp_path):
    with pytest.raises(ConfigError, match="one of them"):
        view_module.Sink().check()
    with pytest.raises(ConfigError, match="one of them"):
        view_module.Sink(save=tmp_path / "a.rrd", serve=True).check()
    with pytest.raises(ConfigError, match="an .rrd file"):
        view_module.Sink(save=tmp_path / "a.png").check()


def test_the_web_viewer_shows_the_recording_in_headless_chromium(store, tmp_path):
    from ga3ce_prep.testing.browser import rerun_web_viewer

    path, ckpt = store
    s = open_store(path)
    web, grpc = free_port(), free_port()
    proc = subprocess.Popen([sys.executable, "-m", "ga3ce_prep.cli", "view", str(path), "-c", str(ckpt), "--serve",
                             "--web-port", str(web), "--grpc-port", str(grpc)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            # started as a script's background job is, SIGINT ignored: Ctrl-C must still stop it
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    page = None
    try:
        url = None
        for line in proc.stderr:
            m = re.search(r"serving the web viewer at (http://\S+)", line)
            if m:
                url = m[1]
                break
        assert url, proc.communicate(timeout=10)
        page = rerun_web_viewer(url, len(s), tmp_path / "viewer.rrd", timeout=240.0)
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            out, err = proc.communicate(timeout=60)
        except subprocess.TimeoutExpired:   # a failure above (page None) is the one to report
            proc.kill()
            out, err = proc.communicate()
            if page is not None:
                pytest.fail(f"`view --serve` did not stop within 60 s of Ctrl-C: {err[-500:]}")
    assert page.ready, (page.values.get("message"), page.errors[:5])
    assert page.values["panicked"] is False and page.values["message"] == ""   # no crash, no error page
    assert proc.returncode == 0 and "stopped" in err
    back = read_recording(tmp_path / "viewer.rrd", blobs=False)
    assert [r["TextDocument:text"] for r in back.at("/frames/id", "row").values()] == \
        [[str(i)] for i in s.frames["id"].tolist()]
    # the errors the page logged are its fetches of other hosts (fonts, telemetry), refused here
    assert all("Failed to fetch" in e or "ERR_NAME_NOT_RESOLVED" in e for e in page.errors), page.errors[:5]
    shot = cv2.imdecode(np.frombuffer(page.png, np.uint8), cv2.IMREAD_COLOR)
    assert shot.shape[:2] == (800, 1280)
    view3d = shot[60:480, :760]                                # the 3D view drew something: many colours
    assert len(np.unique(view3d.reshape(-1, 3) // 16, axis=0)) > 50
