"""Property-based geometry (hypothesis): projection and back-projection are inverse; the mask
medians do not depend on the order in which pixels are enumerated; the egocentric context does not
change when the scene moves rigidly against the camera, up to the roll about the view axis, and not
at all for a translation with a turn about the camera's vertical axis (the cyclotorsion frame
fixes the roll against the camera's horizontal)."""
import numpy as np
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from ga3ce_prep.geometry import back_project, object_positions, project
from ga3ce_prep.model.egocentric import egocentric_transform

SETTINGS = settings(max_examples=60, deadline=None, derandomize=True)  # the same examples in every run (CI)


def floats(lo, hi):
    return st.floats(lo, hi, allow_nan=False, allow_infinity=False)


@st.composite
def intrinsics(draw) -> np.ndarray:
    fx, fy = draw(floats(10, 5000)), draw(floats(10, 5000))
    cx, cy = draw(floats(0, 4000)), draw(floats(0, 4000))
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])


@SETTINGS
@given(K=intrinsics(), p=arrays(np.float64, (16, 3), elements=floats(-20, 20)),
       z=arrays(np.float64, 16, elements=floats(0.05, 50)))
def test_back_projection_inverts_projection(K, p, z):
    p[:, 2] = z
    uv = project(p, K)
    np.testing.assert_allclose(back_project(uv[:, 0], uv[:, 1], z, K), p, rtol=1e-9, atol=1e-9)


@SETTINGS
@given(K=intrinsics(), uv=arrays(np.float64, (16, 2), elements=floats(-1000, 5000)),
       z=arrays(np.float64, 16, elements=floats(0.05, 50)))
def test_projection_inverts_back_projection(K, uv, z):
    np.testing.assert_allclose(project(back_project(uv[:, 0], uv[:, 1], z, K), K), uv, rtol=1e-9, atol=1e-7)


@st.composite
def mask_scene(draw):
    """A small depth map (some unknown pixels), its sensor validity, a label image and K."""
    h, w = draw(st.integers(2, 12)), draw(st.integers(2, 12))
    depth = draw(arrays(np.float32, (h, w),
                        elements=st.sampled_from([0.0, 0.5, 1.25, 2.0, 3.5]) | floats(0.3, 9.0).map(np.float32)))
    valid = draw(arrays(bool, (h, w)))
    labels = draw(arrays(np.int32, (h, w), elements=st.integers(-1, 4)))
    return depth, valid, labels, draw(intrinsics()), draw(st.integers(1, 4))


def _fields(res):
    return res.xyz, res.area, res.n_valid, res.index, res.n_dropped


@SETTINGS
@given(scene=mask_scene())
def test_mask_medians_do_not_depend_on_pixel_order(scene):
    depth, valid, labels, K, min_points = scene
    res = object_positions(depth, K, labels, valid=valid, min_points=min_points)
    # the transposed image enumerates every mask's pixels in another order: same medians, x and y swapped
    Kt = K[[1, 0, 2]][:, [1, 0, 2]]
    t = object_positions(depth.T.copy(), Kt, labels.T.copy(), valid=valid.T.copy(), min_points=min_points)
    np.testing.assert_array_equal(t.xyz[:, [1, 0, 2]], res.xyz)
    for a, b in zip(_fields(t)[1:], _fields(res)[1:]):
        np.testing.assert_array_equal(a, b)
    # the same masks as a (M, H, W) stack, in a shuffled order: the same rows, shuffled
    ids = np.random.default_rng(int(depth.sum() * 1000) % 2**32).permutation(int(labels.max(initial=-1)) + 1)
    stack = np.stack([labels == i for i in ids]) if len(ids) else np.zeros((0, *labels.shape), bool)
    s = object_positions(depth, K, stack, valid=valid, min_points=min_points)
    order = np.argsort(ids[s.index])
    np.testing.assert_array_equal(ids[s.index][order], res.index)
    np.testing.assert_array_equal(s.xyz[order], res.xyz)
    assert s.n_dropped == res.n_dropped
    # and the order-free definition: numpy's median of each mask's back-projected valid points
    v, u = np.mgrid[:depth.shape[0], :depth.shape[1]]
    pts = back_project(u, v, depth.astype(np.float64), K)
    for row, i in enumerate(res.index):
        m = (labels == i) & valid & (depth > 0)
        np.testing.assert_allclose(res.xyz[row], np.median(pts[m], axis=0), rtol=1e-5, atol=1e-5)


def _rotation(q) -> np.ndarray:
    w, x, y, z = np.asarray(q) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


@st.composite
def person_scene(draw):
    """A person 1-6 m in front of the camera (30 joints around the head, the head width 8-20 cm),
    objects around them, and a view prior not straight up or down."""
    head = np.array([draw(floats(-2, 2)), draw(floats(-1, 1)), draw(floats(1, 6))])
    pose = head + draw(arrays(np.float64, (30, 3), elements=floats(-0.9, 0.9)))
    pose[24] = head + [-0.05, 0, 0]
    pose[28] = head + [draw(floats(0.03, 0.15)), draw(floats(-0.02, 0.02)), draw(floats(-0.02, 0.02))]
    objects = head + draw(arrays(np.float64, (5, 3), elements=floats(-4, 4)))
    view = np.array([draw(floats(-1, 1)), draw(floats(-0.9, 0.9)), draw(floats(-1, 1))])
    st_ok = np.linalg.norm(view) > 0.2 and abs(view[1]) / np.linalg.norm(view) < 0.95
    return pose, objects, head, view if st_ok else np.array([0.3, 0.1, 1.0])


def _ego(pose, objects, head, view):
    def t(a):
        return torch.tensor(a[None], dtype=torch.float64)

    return egocentric_transform(t(view / np.linalg.norm(view)), t(pose), t(objects), t(head))


def _moved(scene, R, shift):
    pose, objects, head, view = scene
    return pose @ R.T + shift, objects @ R.T + shift, head @ R.T + shift, view @ R.T


@SETTINGS
@given(scene=person_scene(), yaw=floats(-np.pi, np.pi), shift=arrays(np.float64, 3, elements=floats(-5, 5)))
def test_egocentric_context_is_invariant_to_a_translation_and_a_turn_about_the_vertical(scene, yaw, shift):
    c, s = np.cos(yaw), np.sin(yaw)
    Ry = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    a, b = _ego(*scene), _ego(*_moved(scene, Ry, shift))
    for name in ("view", "pose", "objects"):
        torch.testing.assert_close(getattr(b, name), getattr(a, name), rtol=1e-7, atol=1e-7, msg=name)
    assert torch.equal(a.joint_valid, b.joint_valid)


@SETTINGS
@given(scene=person_scene(), q=arrays(np.float64, 4, elements=floats(-1, 1)).filter(lambda q: np.linalg.norm(q) > 0.1),
       shift=arrays(np.float64, 3, elements=floats(-5, 5)))
def test_any_rigid_motion_changes_the_egocentric_context_by_a_roll_about_the_view_only(scene, q, shift):
    moved = _moved(scene, _rotation(q), shift)
    a, b = _ego(*scene), _ego(*moved)
    torch.testing.assert_close(b.view, a.view, rtol=0, atol=1e-9)  # z
    pa, pb = (torch.cat([e.pose[0], e.objects[0]]) for e in (a, b))
    torch.testing.assert_close(pb[:, 2], pa[:, 2], rtol=1e-7, atol=1e-7)  # along the view: unchanged
    # across it: the same 2D configuration (every dot product), so one rotation about z maps a to b
    torch.testing.assert_close(pb[:, :2] @ pb[:, :2].T, pa[:, :2] @ pa[:, :2].T, rtol=1e-6, atol=1e-6)

    def cross(p):
        return p[:, None, 0] * p[None, :, 1] - p[:, None, 1] * p[None, :, 0]

    torch.testing.assert_close(cross(pb), cross(pa), rtol=1e-6, atol=1e-6)  # a rotation, not a reflection
