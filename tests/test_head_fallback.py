"""The head stage's fallbacks when the head box has no measured depth: hand-made depth and pose with
known answers, then the synthetic world with head holes (`depth.head_hole_prob`) through the
`synthetic` pipeline, against the truth."""
import numpy as np
import pytest

from ga3ce_prep.errors import FrameError
from ga3ce_prep.frames import DepthMap, FrameRef
from ga3ce_prep.geometry import back_project, head_position
from ga3ce_prep.pipeline import run_pipeline
from ga3ce_prep.skeleton import HEAD_JOINTS, N_JOINTS, J
from ga3ce_prep.stages.base import BackendContext
from ga3ce_prep.stages.head import DepthHead
from ga3ce_prep.store import open_store
from ga3ce_prep.synthetic import generate
from ga3ce_prep.synthetic.config import load_config
from ga3ce_prep.synthetic.truth import TruthReader
from ga3ce_prep.testing.worlds import WORLD_640

K = np.array([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]])
BOX = np.array([40, 10, 60, 30], np.float32)  # centre (50, 20)


def _frame() -> FrameRef:
    return FrameRef(id="f", split="test", scene="s", image_path="x.jpg", K=K, image_size=(100, 100), head_box=BOX)


def _inputs():
    """Measured depth 3.0 m everywhere but the head box (a hole the completion filled with 5.0 m);
    a pose 0.2 m too far (a monocular estimator's distance error): body joints spread over the
    lower image at z = 3.2 m, ears 0.15 m apart at z = 3.2 m (near head surface 3.125 m)."""
    depth = np.full((100, 100), 3.0, np.float32)
    valid = np.ones((100, 100), bool)
    valid[10:31, 40:61] = False
    depth[10:31, 40:61] = 5.0
    pose = np.zeros((N_JOINTS, 3))
    pose[:, 0] = np.linspace(-0.8, 0.8, N_JOINTS)
    pose[:, 1] = np.linspace(0.3, 1.3, N_JOINTS)
    pose[:, 2] = 3.2
    pose[list(HEAD_JOINTS)] = [0.0, -0.9, 3.2]
    pose[J["lear"]], pose[J["rear"]] = [0.075, -0.9, 3.2], [-0.075, -0.9, 3.2]
    return DepthMap(depth, valid), pose


def _head(fallbacks=None, **kw):
    params = {} if fallbacks is None else {"fallbacks": fallbacks}
    return DepthHead(params, BackendContext(data_root=".")).head(_frame(), *kw.values())


def test_each_fallback_gives_its_depth_on_the_box_centre_ray():
    dm, pose = _inputs()
    ray = back_project(50.0, 20.0, 1.0, K)
    # body joints 5 cm behind the 3.0 m surface vote the pose 0.15 m nearer: 3.125 - 0.15
    r = _head(None, depth=dm, pose=pose)
    assert r.source == "pose_depth"
    np.testing.assert_allclose(r.value, 2.975 * ray, atol=1e-5)
    r = _head(["pose"], depth=dm, pose=pose)
    assert r.source == "pose"
    np.testing.assert_allclose(r.value, 3.125 * ray, atol=1e-5)
    r = _head(["completed"], depth=dm, pose=pose)
    assert r.source == "completed"
    np.testing.assert_allclose(r.value, 5.0 * ray, atol=1e-5)
    # no pose: the completed depth; nothing allowed: the frame fails
    r = _head(None, depth=dm, pose=np.full((N_JOINTS, 3), np.nan))
    assert r.source == "completed"
    with pytest.raises(FrameError, match="tried measured depth"):
        _head([], depth=dm, pose=pose)
    # without both ears the mean of the head joints; measured depth wins whenever there is some
    no_ears = pose.copy()
    no_ears[[J["lear"], J["rear"]]] = np.nan
    assert _head(["pose"], depth=dm, pose=no_ears).value[2] == pytest.approx(3.2)
    measured = DepthMap(dm.depth, np.ones_like(dm.valid))
    r = _head(None, depth=measured, pose=pose)
    assert r.source == "measured"
    np.testing.assert_allclose(r.value, head_position(measured.depth, K, BOX, window_fracs=(0.2,), min_points=3))


def test_head_holes_are_kept_through_the_pose_and_land_near_the_truth(tmp_path):
    cfg = load_config("gfie", overrides={"depth": {"head_hole_prob": 0.5}})
    world = tmp_path / "w"
    generate("gfie", world, progress=False, config=cfg, **WORLD_640)
    # an RGB-D-refined pose (1 cm a joint): the fallback's own error, not the oracle's default noise
    run_pipeline("synthetic", world, tmp_path / "s.zarr", progress=False,
                 overrides=["stages.pose.params.sigma_body=0.01", "stages.pose.params.sigma_face=0.01"])
    s = open_store(tmp_path / "s.zarr")
    names = s.source_names["head"]
    assert names == ["measured", "pose_depth", "pose", "completed"]
    src = np.asarray(names)[s.frames["head_source"]]
    assert len(s) == 8 and s.attrs["summary"]["frames_kept"] == 8          # nothing dropped
    assert sorted(src.tolist()) == ["measured"] * 3 + ["pose_depth"] * 5   # pinned: 5 of 8 frames holed
    truth = TruthReader(world / "truth.h5")
    for i in np.flatnonzero(src == "pose_depth"):
        t = truth.get(s.frames["id"][i])
        exact = np.asarray(t.depth, np.float32)
        true_pos = head_position(exact, t.K, s.frames["head_box"][i], valid=exact > 0, window_fracs=(0.2, 0.5, 1.0),
                                 min_points=3)
        assert np.linalg.norm(s.frames["head_pos"][i] - true_pos) < 0.15
