"""Seeded, calibrated noise of the oracle backends."""
import numpy as np
import pytest

from ga3ce_prep.geometry import angular_error_deg, normalize
from ga3ce_prep.skeleton import HEAD_JOINTS
from ga3ce_prep.stages.oracle_noise import frame_rng, noisy_pose, noisy_view, rice_sigma


def _directions(n, max_offset_deg, seed=0):
    """n truth gazes and head directions max_offset_deg or less apart (eye-in-head offsets)."""
    rng = np.random.default_rng(seed)
    g = normalize(rng.standard_normal((n, 3)))
    axis = normalize(np.cross(g, rng.standard_normal((n, 3))))
    ang = np.radians(rng.uniform(0, max_offset_deg, n))[:, None]
    h = g * np.cos(ang) + np.cross(axis, g) * np.sin(ang)  # rotate g about axis (axis is orthogonal to g)
    return g, normalize(h)


def _mean_error(mean_deg, head_weight, n=4000):
    g, h = _directions(n, 25.0)
    v = np.stack([noisy_view(g[i], h[i], frame_rng(3, "view/oracle", f"f{i}"), mean_deg, head_weight)
                  for i in range(n)])
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 1, atol=1e-5)
    return angular_error_deg(v, g), angular_error_deg(v, h)


def test_view_noise_mean_error_matches_the_setting():
    for mean_deg in (20.0, 40.0):
        err, _ = _mean_error(mean_deg, 0.0)
        assert abs(err.mean() - mean_deg) < 1.0, (mean_deg, err.mean())


def test_view_noise_pulled_toward_head_keeps_the_mean_error_and_correlates_with_head():
    err, err_head = _mean_error(20.0, 0.5)
    assert abs(err.mean() - 20.0) < 1.0, err.mean()
    err0, err_head0 = _mean_error(20.0, 0.0)
    assert err_head.mean() < err_head0.mean() - 3.0  # v sits closer to the head direction


def test_rice_sigma_inverts_the_rice_mean():
    rng = np.random.default_rng(0)
    for offset, mean in ((0.0, 0.35), (0.2, 0.35), (0.34, 0.35), (0.02, 0.7)):
        s = rice_sigma(offset, mean)
        e = np.array([offset, 0.0]) + s * rng.standard_normal((200_000, 2))
        assert abs(np.hypot(e[:, 0], e[:, 1]).mean() - mean) < 0.003
    assert rice_sigma(0.5, 0.35) == 0.0


def test_noise_depends_only_on_seed_and_frame_id():
    a = [frame_rng(0, "pose/oracle", f"id{i}").standard_normal(3) for i in range(5)]
    b = [frame_rng(0, "pose/oracle", f"id{i}").standard_normal(3) for i in reversed(range(5))][::-1]
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(frame_rng(0, "pose/oracle", "id0").standard_normal(3),
                           frame_rng(1, "pose/oracle", "id0").standard_normal(3))
    assert not np.allclose(frame_rng(0, "pose/oracle", "id0").standard_normal(3),
                           frame_rng(0, "view/oracle", "id0").standard_normal(3))


def test_pose_noise_is_larger_on_the_face():
    truth = np.zeros((30, 3))
    d = np.stack([noisy_pose(truth, frame_rng(0, "p", str(i)), 0.02, 0.05) for i in range(2000)])
    face = list(HEAD_JOINTS)
    body = [j for j in range(30) if j not in face]
    assert abs(d[:, face].std() - 0.05) < 0.003
    assert abs(d[:, body].std() - 0.02) < 0.001
    scaled = noisy_pose(np.ones((30, 3)), frame_rng(0, "p", "x"), 0.0, 0.0, scale_bias=1.1)
    np.testing.assert_allclose(scaled, 1.1, rtol=1e-6)


def _truth_poses(world) -> np.ndarray:
    from ga3ce_prep.synthetic import TruthReader

    with TruthReader(world) as tr:
        return tr.array("pose").astype(np.float64)


def test_articulated_pose_keeps_the_skeleton_and_moves_the_face_as_one(synth_world):
    """Rotations only: every bone keeps its length and the face joints their distances to each
    other and to the head joint; the error is the estimator's size (MeTRAbs' 61.9 mm on 3DPW)."""
    from ga3ce_prep.skeleton import PARENTS
    from ga3ce_prep.stages.oracle_noise import articulated_pose

    poses = _truth_poses(synth_world)
    face = list(HEAD_JOINTS)
    errors = []
    for i, P in enumerate(poses):
        for k in range(40):
            Q = articulated_pose(P, frame_rng(0, "t", f"{i}/{k}"), frame_rng(0, "s", str(i)), 3.0, 3.0)
            Q = Q.astype(np.float64)
            errors.append(np.linalg.norm((Q - Q[0]) - (P - P[0]), axis=1).mean())
            bones = list(range(1, len(PARENTS)))
            np.testing.assert_allclose(np.linalg.norm(Q[bones] - Q[[PARENTS[j] for j in bones]], axis=1),
                                       np.linalg.norm(P[bones] - P[[PARENTS[j] for j in bones]], axis=1), atol=1e-5)
            dq = np.linalg.norm(Q[face][:, None] - Q[face][None], axis=-1)
            dp = np.linalg.norm(P[face][:, None] - P[face][None], axis=-1)
            np.testing.assert_allclose(dq, dp, atol=1e-5)
    assert 0.050 < np.mean(errors) < 0.075       # root-relative mean per-joint error, metres


def test_articulated_pose_persists_within_a_recording():
    from ga3ce_prep.stages.oracle_noise import articulated_pose

    P = np.stack([np.linspace(-0.3, 0.3, 30), np.linspace(-0.8, 0.9, 30), np.full(30, 3.0)], 1)
    session = lambda: frame_rng(0, "s", "rec1")   # noqa: E731
    a = articulated_pose(P, frame_rng(0, "f", "1"), session(), 3.0, 3.0, 0.1, 0.02, persistence=1.0)
    b = articulated_pose(P, frame_rng(0, "f", "2"), session(), 3.0, 3.0, 0.1, 0.02, persistence=1.0)
    c = articulated_pose(P, frame_rng(0, "f", "2"), frame_rng(0, "s", "rec2"), 3.0, 3.0, 0.1, 0.02, persistence=1.0)
    d = articulated_pose(P, frame_rng(0, "f", "2"), session(), 3.0, 3.0, 0.1, 0.02, persistence=0.0)
    np.testing.assert_array_equal(a, b)                        # all of it the recording's
    assert np.abs(a - c).max() > 1e-3 and np.abs(a - d).max() > 1e-3
    e = articulated_pose(P, frame_rng(0, "f", "1"), session(), 0.0, 0.0, 0.1, 0.0)
    shift = e[0] - P[0]
    assert abs(np.dot(shift, normalize(P[0]))) == pytest.approx(np.linalg.norm(shift), rel=1e-5)  # along the ray


def test_articulated_oracle_backend_runs_from_a_pipeline(synth_world, tmp_path):
    from ga3ce_prep.pipeline import load_pipeline

    conf = load_pipeline("synthetic", synth_world, check_files=False,
                         overrides={"stages.pose": {"backend": "oracle-articulated", "params": {"persistence": 0.5}}})
    backend = conf.stages["pose"].make(synth_world)
    from ga3ce_prep.datasets import open_dataset

    frames = list(open_dataset("gfie", synth_world).frames())[:2]
    a, b = backend.pose(frames[0]), backend.pose(frames[0])
    np.testing.assert_array_equal(a, b)                        # seeded by the frame
    assert a.shape == (30, 3) and a.dtype == np.float32 and 0 < np.abs(a - backend.pose(frames[1])).max()


def test_turn_oracle_errs_by_how_far_the_head_turns(synth_world):
    """`oracle-turn`: v errs front_error_deg with the face to the camera, back_error_deg facing away."""
    from ga3ce_prep.datasets import open_dataset
    from ga3ce_prep.pipeline import load_pipeline
    from ga3ce_prep.stages.view import turn_from_camera
    from ga3ce_prep.synthetic.truth import TruthReader

    assert turn_from_camera(np.array([0.0, 0.0, -1.0]), np.array([0.0, 0.0, 3.0])) == pytest.approx(0.0)
    assert turn_from_camera(np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 3.0])) == pytest.approx(90.0)
    assert turn_from_camera(np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 3.0])) == pytest.approx(180.0)
    conf = load_pipeline("synthetic-calibrated", synth_world, check_files=False,
                         overrides=["stages.view.params.front_error_deg=10", "stages.view.params.back_error_deg=30",
                                    "stages.view.params.head_weight=0"])
    view = conf.stages["view"].make(synth_world)
    truth = TruthReader(synth_world / "truth.h5")
    frames = list(open_dataset("gfie", synth_world).frames())
    assert len(frames) >= 10
    want, turns = [], []
    for f in frames:
        rec = truth.get(f.id)
        want.append(view.mean_error_deg(rec.head_dir, rec.head_center))
        turns.append(turn_from_camera(rec.head_dir, rec.head_center))
    want, turns = np.array(want), np.array(turns)
    at = np.array([0.0, 0.5, 3.0])                  # a head 3 m ahead, facing the camera, sideways, away
    assert [view.mean_error_deg(d, at) for d in (-normalize(at), np.array([1.0, 0, 0]), normalize(at))] \
        == pytest.approx([10.0, 20.0, 30.0])
    np.testing.assert_allclose(want, 10 + 20 * (1 - np.cos(np.radians(turns))) / 2, atol=1e-9)
    # each frame's error is drawn around its own mean: many draws of one frame per end of the range
    for i in (int(np.argmin(turns)), int(np.argmax(turns))):
        rec = truth.get(frames[i].id)
        errs = [angular_error_deg(noisy_view(normalize(rec.gaze), rec.head_dir, frame_rng(k, "view/oracle", "x"),
                                             want[i]), normalize(rec.gaze)) for k in range(3000)]
        assert np.mean(errs) == pytest.approx(want[i], rel=0.05)
    v = view.view(frames[0])
    assert v.shape == (3,) and abs(np.linalg.norm(v) - 1) < 1e-5
