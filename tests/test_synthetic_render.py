"""Synthetic world, geometry of rendering: pixel convention, projected head boxes, depth noise and
holes at their configured rates."""
import cv2
import numpy as np
import open3d as o3d
import pytest

from ga3ce_prep.geometry import back_project, project
from ga3ce_prep.synthetic.camera import Camera, ellipsoid_bbox, look_rotation
from ga3ce_prep.synthetic.config import DepthConfig, RenderConfig
from ga3ce_prep.synthetic.noise import NoiseBank, depth_sensor, depth_sigma
from ga3ce_prep.synthetic.render import StaticScene, render_static
from ga3ce_prep.synthetic.room import Instance, Room

K = np.array([[525.0, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]])


def _sphere_room(centre, radius):
    m = o3d.geometry.TriangleMesh.create_sphere(radius=radius, resolution=200)
    v = (np.asarray(m.vertices) + centre).astype(np.float32)
    inst = Instance(id=0, kind="object", shape="sphere", vertices=v, triangles=np.asarray(m.triangles, np.int32),
                    albedo=np.array([0.5, 0.5, 0.5], np.float32), size=2 * radius, centroid=np.asarray(centre),
                    samples=v[:10])
    return Room(size=np.array([10.0, 10.0, 3.0]), instances=[inst], surfaces=[], free=np.zeros((1, 1), bool),
                light=np.array([0.0, 0.0, -1.0]))


def test_sphere_centre_pixel_back_projects_onto_the_truth():
    """Pixel (u, v) is the image point (u, v) under K: the sphere's centre pixel, back-projected
    with its rendered depth, lands within 1 mm of the exact surface point on that ray. Casting
    through pixel centres (u + 0.5, Open3D's create_rays_pinhole) would miss by about 2 mm."""
    u0, v0, z0, r = 402, 171, 2.0, 0.2
    centre = back_project(np.float64(u0), np.float64(v0), z0, K)
    cam = Camera(K=K, width=640, height=480, R=np.eye(3), C=np.zeros(3))  # camera frame = world frame
    view = render_static(StaticScene(_sphere_room(centre, r)), cam, RenderConfig())
    assert view.instance[v0, u0] == 0
    p = back_project(np.float64(u0), np.float64(v0), float(view.depth[v0, u0]), K)
    exact = centre - r * centre / np.linalg.norm(centre)
    assert np.linalg.norm(p - exact) < 1e-3
    p_half = back_project(u0 + 0.5, v0 + 0.5, float(view.depth[v0, u0]), K)
    assert np.linalg.norm(p_half - exact) > 1e-3  # the test can tell the conventions apart
    # the silhouette's pixel extent is the exact projected outline's (pixel u is inside iff the
    # image point u is): first/last pixels are ceil/floor of the tangent lines
    vv, uu = np.nonzero(view.instance == 0)
    x1, y1, x2, y2 = ellipsoid_bbox(K, centre, np.eye(3), np.full(3, r))
    assert (uu.min(), vv.min(), uu.max(), vv.max()) == (np.ceil(x1), np.ceil(y1), np.floor(x2), np.floor(y2))


def test_camera_rays_have_unit_z_and_match_projection():
    R = look_rotation(np.array([1.0, 0.3, -0.4]))
    cam = Camera(K=K, width=64, height=48, R=R, C=np.array([1.0, 2.0, 1.5]))
    rays = cam.rays()
    d_cam = rays[..., 3:].astype(np.float64) @ R.T
    np.testing.assert_allclose(d_cam[..., 2], 1.0, atol=1e-6)
    pts = rays[..., :3] + 2.5 * rays[..., 3:]
    uv = cam.project(pts)
    np.testing.assert_allclose(uv[7, 11], [11, 7], atol=1e-4)
    assert abs(R[0, 2]) < 1e-12  # x axis horizontal: no roll
    rolled = look_rotation(np.array([1.0, 0.3, -0.4]), roll=np.radians(5))
    assert abs(rolled[0, 2]) > 0.05


def test_ellipsoid_bbox_is_tight():
    rng = np.random.default_rng(0)
    for _ in range(5):
        c = rng.uniform([-1, -0.5, 2], [1, 0.5, 5])
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        ax = rng.uniform(0.07, 0.12, 3)
        box = ellipsoid_bbox(K, c, q, ax)
        # dense surface samples
        s = rng.normal(size=(200000, 3))
        s /= np.linalg.norm(s, axis=1, keepdims=True)
        uv = project(c + (s * ax) @ q.T, K)
        ref = np.concatenate([uv.min(0), uv.max(0)])
        np.testing.assert_allclose(box, ref, atol=0.05)


def _flat_views(H=120, W=160):
    depth = np.full((H, W), 2.0, np.float32)
    depth[:, W // 2:] = 3.0  # a depth step: an edge down the middle
    depth[:10] = 7.0         # out of range
    lum = np.full((H, W), 0.5, np.float32)
    lum[60:, :40] = 0.02     # dark
    shiny = np.zeros((H, W), bool)
    shiny[60:, 100:] = True  # shiny
    return depth, lum, shiny


def test_depth_holes_follow_configured_rates():
    depth, lum, shiny = _flat_views()
    cfg = DepthConfig(edge_hole_prob=0.7, dark_hole_prob=0.4, shiny_hole_prob=0.25, blob_rate=0.0,
                      edge_width=1, max_range=5.5)
    rng = np.random.default_rng(1)
    bank = NoiseBank(rng, *depth.shape)
    frac = {"dark": [], "shiny": [], "edge": [], "plain": []}
    for _ in range(30):
        d, holes = depth_sensor(depth, lum, shiny, cfg, bank, rng)
        hole = d == 0
        assert hole[:10].all()  # out of range
        assert np.array_equal(hole, holes.any)
        frac["dark"].append(hole[62:, :38].mean())
        frac["shiny"].append(hole[62:, 102:].mean())
        frac["edge"].append(hole[12:58, 79:81].mean())
        frac["plain"].append(hole[12:58, 10:70].mean())
    assert abs(np.mean(frac["dark"]) - 0.4) < 0.03
    assert abs(np.mean(frac["shiny"]) - 0.25) < 0.03
    assert abs(np.mean(frac["edge"]) - 0.7) < 0.05
    assert np.mean(frac["plain"]) == 0.0
    # blobs: blob_rate blobs per frame on average (Poisson), each a filled ellipse
    cfg2 = DepthConfig(edge_hole_prob=0, dark_hole_prob=0, shiny_hole_prob=0, blob_rate=3.0, max_range=10)
    n_blob = [cv2.connectedComponents(depth_sensor(depth, lum, shiny, cfg2, bank, rng)[1].blob.astype(np.uint8))[0] - 1
              for _ in range(200)]
    assert abs(np.mean(n_blob) - 3.0) < 0.4


def test_depth_noise_grows_with_z_squared_and_is_quantised():
    H, W = 120, 160
    cfg = DepthConfig(edge_hole_prob=0, dark_hole_prob=0, shiny_hole_prob=0, blob_rate=0, quantize_mm=True)
    rng = np.random.default_rng(2)
    bank = NoiseBank(rng, H, W)
    for z in (1.0, 4.0):
        depth = np.full((H, W), z, np.float32)
        d, _ = depth_sensor(depth, np.full((H, W), 0.5, np.float32), np.zeros((H, W), bool), cfg, bank, rng)
        err = d - z
        assert abs(err.std() / depth_sigma(z, cfg) - 1) < 0.1
        np.testing.assert_allclose(d * 1000, np.round(d * 1000), atol=1e-3)


def test_noise_bank_crops_vary():
    rng = np.random.default_rng(3)
    bank = NoiseBank(rng, 12, 16)
    a, b = bank.crop(bank.depth, rng), bank.crop(bank.depth, rng)
    assert a.shape == (12, 16)
    assert not np.array_equal(a, b)


@pytest.mark.parametrize("z", [0.3, 6.0])
def test_out_of_range_always_dropped(z):
    H, W = 8, 8
    cfg = DepthConfig(blob_rate=0)
    rng = np.random.default_rng(0)
    d, holes = depth_sensor(np.full((H, W), z, np.float32), np.full((H, W), 0.5, np.float32),
                            np.zeros((H, W), bool), cfg, NoiseBank(rng, H, W), rng)
    assert (d == 0).all()
    assert holes.out_of_range.all()
