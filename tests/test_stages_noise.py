"""Seeded, calibrated noise of the oracle backends."""
import numpy as np

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
