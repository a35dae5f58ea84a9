"""Synthetic world: the truth is geometrically consistent (gaze from the eye to the target, face
joints on the head, depth at an instance mask on that object's surface, camera without roll), the
gaze behaviour follows its knobs, and rooms follow the object count and size knobs."""
import numpy as np
import open3d as o3d
import pytest

from ga3ce_prep.geometry import angular_error_deg, back_project, depth_to_points, project
from ga3ce_prep.synthetic import generate
from ga3ce_prep.synthetic.camera import intrinsics
from ga3ce_prep.synthetic.config import DepthConfig, load_config
from ga3ce_prep.synthetic.noise import depth_sigma
from ga3ce_prep.synthetic.room import build_room
from ga3ce_prep.synthetic.stats import object_snap, world_statistics
from ga3ce_prep.synthetic.truth import TruthReader
from ga3ce_prep.synthetic.world import Scene

W, H = 160, 120


@pytest.fixture(scope="module")
def gfie_world(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth_world") / "gfie"
    generate("gfie", out, scenes=6, frames_per_scene=8, seed=11, width=W, height=H, progress=False)
    with TruthReader(out) as tr:
        yield out, tr


def test_gaze_points_from_eye_to_target_and_is_unit(gfie_world):
    _, tr = gfie_world
    g, e, t = tr.gaze, tr.eye, tr.gaze_target
    np.testing.assert_allclose(np.linalg.norm(g, axis=1), 1.0, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(tr.head_dir, axis=1), 1.0, atol=1e-9)
    d = t - e
    np.testing.assert_allclose(g, d / np.linalg.norm(d, axis=1, keepdims=True), atol=1e-9)
    # the eye is the midpoint of the two eye joints (huge8: 25 leye, 27 reye)
    np.testing.assert_allclose(e, 0.5 * (tr.pose[:, 25] + tr.pose[:, 27]), atol=1e-9)


def test_face_joints_lie_on_the_head_ellipsoid(gfie_world):
    _, tr = gfie_world
    for i in range(len(tr)):
        R, ax, c = tr.head_R[i], tr.head_axes[i], tr.head_center[i]
        local = (tr.pose[i, [25, 26, 27, 28, 29]] - c) @ R / ax
        np.testing.assert_allclose(np.linalg.norm(local, axis=1), 1.0, atol=1e-6)
        # eyes in front, ears at the sides, head top above: oriented by the head direction
        assert (local[[0, 2], 0] > 0.8).all()
        assert local[1, 1] > 0.9
        assert local[3, 1] < -0.9
        np.testing.assert_allclose(R[:, 0], tr.head_dir[i], atol=1e-9)
    # nose to right ear (GA3CE's head width pair) about 0.14 m at 1.75 m
    hw = np.linalg.norm(tr.pose[:, 24] - tr.pose[:, 28], axis=1) / tr.person_height * 1.75
    np.testing.assert_allclose(hw, 0.137, atol=0.005)


def test_projected_truth_is_the_written_2d(gfie_world):
    _, tr = gfie_world
    np.testing.assert_allclose(project(tr.eye, tr.K[0]), tr.eye_2d, atol=1e-9)
    np.testing.assert_allclose(project(tr.gaze_target, tr.K[0]), tr.gaze_2d, atol=1e-9)
    # head box contains the projected eyes and lies in the image
    hb = tr.head_box
    e2 = project(tr.pose[:, [25, 27]], tr.K[0])
    assert (e2[..., 0] >= hb[:, None, 0] - 1e-6).all()
    assert (e2[..., 0] <= hb[:, None, 2] + 1e-6).all()
    assert (hb[:, :2] >= 0).all()
    assert (hb[:, 2] <= W - 1).all()
    assert (hb[:, 3] <= H - 1).all()


def test_object_targets_are_on_the_rendered_surface(gfie_world):
    out, tr = gfie_world
    kinds = tr.target_kind
    assert (kinds == 0).mean() > 0.5
    checked = n_sensor = 0
    for i in np.flatnonzero((kinds == 0) & tr.target_visible):
        u, v = np.round(tr.gaze_2d[i]).astype(int)
        inst = tr.instance(i)
        assert inst[v, u] == tr.target_instance[i]
        p = back_project(np.float64(u), np.float64(v), float(tr.depth(i)[v, u]), tr.K[i])
        # the pixel's ray passes within half a pixel of the target: a few mm at these distances
        tol = 0.01 + 2.0 * tr.gaze_target[i, 2] / tr.K[i][0, 0]
        assert np.linalg.norm(p - tr.gaze_target[i]) < tol
        # the written sensor depth agrees within its noise (where it is not a hole)
        z = float(np.load(out / "depth" / f"{tr.frame_ids[i]}.npy")[v, u])
        if np.isfinite(z):
            q = back_project(np.float64(u), np.float64(v), z, tr.K[i])
            assert np.linalg.norm(q - tr.gaze_target[i]) < tol + 4 * depth_sigma(z, DepthConfig())
            n_sensor += 1
        checked += 1
    assert checked >= 10
    assert n_sensor >= 5


def test_instance_masks_back_project_onto_their_meshes():
    """Rebuild a scene and check that every visible object's masked depth lies on its mesh."""
    cfg = load_config("gfie")
    K = intrinsics(cfg.camera, W, H)
    scene = Scene("gfie", cfg, K, W, H, np.random.default_rng(5))
    step = next(scene.steps(1))
    cam, view = scene.cameras[0], step.views[0]
    pts = depth_to_points(view.depth, K).reshape(-1, 3).astype(np.float64)
    pts_w = pts @ cam.R + cam.C  # camera -> world
    inst = view.instance.ravel()
    n_checked = 0
    for obj in scene.room.instances:
        sel = inst == obj.id
        if sel.sum() < 5:
            continue
        s = o3d.t.geometry.RaycastingScene()
        s.add_triangles(o3d.core.Tensor(obj.vertices), o3d.core.Tensor(obj.triangles.astype(np.uint32)))
        d = s.compute_distance(o3d.core.Tensor(pts_w[sel].astype(np.float32))).numpy()
        assert d.max() < 2e-3, (obj.kind, obj.shape, d.max())
        n_checked += 1
    assert n_checked >= 5
    # the person mask is on the person mesh
    sel = inst == scene.room.person_id
    s = o3d.t.geometry.RaycastingScene()
    s.add_triangles(o3d.core.Tensor(step.mesh[0]), o3d.core.Tensor(step.mesh[1].astype(np.uint32)))
    assert sel.sum() > 20
    assert s.compute_distance(o3d.core.Tensor(pts_w[sel].astype(np.float32))).numpy().max() < 2e-3


def test_cameras_have_no_roll_and_see_the_head(gfie_world):
    _, tr = gfie_world
    assert np.abs(tr.R_w2c[:, 0, 2]).max() < 1e-12  # camera x axis horizontal (world z up)
    d = np.linalg.norm(tr.cam_center[:, :2] - (tr.pose[:, 15] @ tr.R_w2c[0] * 0)[:, :2], axis=1)
    assert d.shape[0] == len(tr)
    dist = np.linalg.norm(tr.head_center, axis=1)
    assert (dist > 1.0).all()
    assert (dist < 7.0).all()
    cfg = load_config("gfie", overrides={"camera": {"roll": 10.0}})
    K = intrinsics(cfg.camera, W, H)
    rolls = [abs(Scene("gfie", cfg, K, W, H, np.random.default_rng(s)).cameras[0].R[0, 2]) for s in range(3)]
    assert max(rolls) > 1e-3


def test_eye_in_head_offset_follows_the_knobs(tmp_path):
    def offsets(overrides):
        out = tmp_path / str(len(list(tmp_path.iterdir())))
        cfg = load_config("gfie", overrides=overrides)
        generate("gfie", out, scenes=3, frames_per_scene=12, seed=2, width=W, height=H, config=cfg, progress=False)
        with TruthReader(out) as tr:
            return angular_error_deg(tr.gaze, tr.head_dir), angular_error_deg(tr.head_dir, tr.chest_dir)

    off, turn = offsets({"gaze": {"eye_offset_max": 12.0}})
    assert off.max() <= 12.0 + 0.5
    off, _ = offsets({"gaze": {"head_follow": [1.0, 1.0], "head_jitter": 0.0, "head_smoothing": 0.0}})
    # the head points at the target, but for turns beyond the neck's range (targets far to the
    # side of a walking person, or at the feet)
    assert np.mean(off < 1.0) > 0.8
    assert np.median(off) < 0.5
    off, turn = offsets({"gaze": {"head_follow": [0.2, 0.3], "eye_offset_max": 40.0}})
    assert np.mean(off > turn) > 0.5
    assert off.max() > 15


def test_world_statistics(gfie_world):
    _, tr = gfie_world
    s = world_statistics(tr)
    assert 10 <= s["objects_per_frame"] <= 60
    assert abs(s["target_object"] + s["target_space"] + s["target_out_of_view"] - 1) < 1e-9
    assert 3 < s["eye_in_head_offset_mean_deg"] <= 25.5
    # the objects carry gaze signal: snapping a 20-degree noisy v to the nearest visible object
    # brings object-target frames closer to the truth
    snap = object_snap(tr, view_error_deg=20.0)
    assert abs(snap["v_error_deg"] - 20.0) < 3.0
    assert snap["snap_error_object_targets_deg"] < snap["v_error_object_targets_deg"] - 1.0


@pytest.mark.parametrize("count,size", [((12, 12), (0.05, 0.1)), ((40, 40), (0.2, 0.3))])
def test_object_counts_and_sizes_follow_config(count, size):
    cfg = load_config("gfie", overrides={"objects": {"count": list(count), "size": list(size)}})
    for seed in range(3):
        room = build_room(cfg, np.random.default_rng(seed))
        objs = [i for i in room.instances if i.kind == "object"]
        assert len(objs) == count[0]
        sizes = np.array([o.size for o in objs])
        ext = np.array([(o.vertices.max(0) - o.vertices.min(0)).max() for o in objs])
        assert (sizes <= size[1] + 1e-6).all()
        # largest mesh extent (a rotated box can be wider than its longest side, a flat torus is L)
        assert (ext <= np.sqrt(2) * size[1] + 1e-3).all()
        assert np.mean(sizes >= size[0] - 1e-6) > 0.8  # shelf headroom may shrink a few
        # objects rest on a surface: their bottom is at a surface height or the floor
        zs = {0.0} | {round(s.z, 4) for s in room.surfaces}
        for o in objs:
            assert min(abs(o.vertices[:, 2].min() - z) for z in zs) < 1e-3


def test_clustering_knob_concentrates_objects():
    def spread(c):
        d = []
        for seed in range(4):
            cfg = load_config("gfie", overrides={"objects": {"count": [20, 20], "size": [0.04, 0.1], "clustering": c}})
            room = build_room(cfg, np.random.default_rng(seed))
            xy = np.array([o.centroid[:2] for o in room.instances if o.kind == "object"])
            d.append(np.median(np.linalg.norm(xy[:, None] - xy[None], axis=2)))
        return np.mean(d)

    assert spread(0.95) < 0.7 * spread(0.0)


def test_generate_stays_a_function_once_its_module_is_loaded():
    """`ga3ce_prep.synthetic.generate` is the documented entry point; a submodule of that name would
    replace it on the package when first imported (a second call then raised "'module' object is not
    callable")."""
    import importlib

    import ga3ce_prep.synthetic as synthetic

    importlib.import_module("ga3ce_prep.synthetic.generation")
    assert callable(synthetic.generate) and synthetic.generate.__module__ == "ga3ce_prep.synthetic"
