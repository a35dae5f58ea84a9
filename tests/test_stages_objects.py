"""The geometry stages on the synthetic world: oracle object medians, head position, geometric recall."""
import numpy as np
import pytest

from ga3ce_prep.geometry import back_project
from ga3ce_prep.pipeline import run_pipeline
from ga3ce_prep.store import open_store
from ga3ce_prep.synthetic.truth import TruthReader
from ga3ce_prep.testing.worlds import SMALL


def _expected_medians(truth, fid, depth, valid, K, kinds=("object", "furniture"), min_points=10):
    """Per truth instance of the kinds, the per-axis median of its valid back-projected points,
    in instance-id order: computed here independently, one mask at a time."""
    rec = truth.get(fid)
    names = truth.object_kinds
    out = []
    for inst, kind in zip(rec.objects.instance, rec.objects.kind):
        if names[kind] not in kinds:
            continue
        v, u = np.nonzero((rec.instance == inst) & valid)
        if len(v) < min_points:
            continue
        pts = back_project(u.astype(np.float64), v.astype(np.float64), depth[v, u].astype(np.float64), K)
        out.append(np.median(pts, axis=0))
    return np.array(out).reshape(-1, 3)


@pytest.mark.parametrize("depth_backend", ["oracle", "sensor"])
def test_oracle_objects_equal_truth_mask_medians(synth_world, tmp_path, depth_backend):
    out = tmp_path / "s.zarr"
    over = [] if depth_backend == "sensor" else [
        "stages.depth.backend=oracle", "stages.depth.params={truth: '{data}/truth.h5'}"]
    run_pipeline("synthetic-oracle", synth_world, out, overrides=over, progress=False)
    s = open_store(out)
    truth = TruthReader(synth_world / "truth.h5")
    assert s.attrs["stages"]["objects"]["oracle"] is True
    n_checked = 0
    for i, fid in enumerate(s.frames["id"]):
        K = s.frames["K"][i].astype(np.float64)
        if depth_backend == "oracle":
            depth = truth.get(fid).depth
            valid = depth > 0
        else:  # the raw sensor file: medians use measured pixels only (NaN holes, range 0.1-10 m)
            depth = np.load(synth_world / "depth" / f"{fid}.npy")  # GFIE ids are <split>/scene<N>/<frame>
            valid = np.isfinite(depth) & (depth >= 0.1) & (depth <= 10.0)
            depth = np.where(valid, depth, 0)
        exp = _expected_medians(truth, fid, depth, valid, K)
        got = s.objects_of(i)
        assert got.shape == exp.shape, fid
        np.testing.assert_allclose(got, exp, rtol=0, atol=2e-5)
        n_checked += len(exp)
    assert n_checked > 30


def test_head_position_within_2cm_of_the_true_head_centre_depth_point(synth_world_640, tmp_path):
    """Frames with valid depth: the sensor measured the head box centre pixel."""
    world = synth_world_640
    out = tmp_path / "s.zarr"
    run_pipeline("synthetic-oracle", world, out, progress=False)
    s = open_store(out)
    truth = TruthReader(world / "truth.h5")
    errs = []
    for i, fid in enumerate(s.frames["id"]):
        x1, y1, x2, y2 = s.frames["head_box"][i]
        cu, cv = 0.5 * (x1 + x2), 0.5 * (y1 + y2)
        r, c = int(round(cv)), int(round(cu))
        if not np.isfinite(np.load(world / "depth" / f"{fid}.npy")[r, c]):
            continue
        z = truth.get(fid).depth[r, c]
        p = back_project(cu, cv, z, s.frames["K"][i].astype(np.float64))
        errs.append(np.linalg.norm(s.frames["head_pos"][i] - p))
    assert len(errs) >= 5
    assert max(errs) < 0.02, errs
    assert np.median(errs) < 0.01


def test_geometric_segmenter_finds_true_objects(synth_world, tmp_path):
    """At 160x120 (stride 1) a floor well below the 640x480 figure in docs/pipeline.md."""
    run_pipeline("synthetic-oracle", synth_world, tmp_path / "o.zarr", progress=False)
    run_pipeline("synthetic", synth_world, tmp_path / "g.zarr", overrides=SMALL, progress=False)
    o, g = open_store(tmp_path / "o.zarr"), open_store(tmp_path / "g.zarr")
    assert g.frames["id"].tolist() == o.frames["id"].tolist()
    hit = tot = 0
    for i in range(len(o)):
        T, G = o.objects_of(i), g.objects_of(i)
        tot += len(T)
        if len(T) and len(G):
            hit += int((np.linalg.norm(T[:, None] - G[None], axis=-1).min(1) < 0.10).sum())
    assert tot > 30
    assert hit / tot > 0.3, (hit, tot)
    assert g.attrs["stages"]["objects"]["backend"] == "geometric"


def test_median_pixels_measured_or_completed_on_a_hand_made_mask(tmp_path):
    """One 21-pixel mask: 10 measured pixels at 2 m, 11 filled-in pixels at 1 m."""
    from dataclasses import dataclass

    from ga3ce_prep.frames import DepthMap, FrameRef
    from ga3ce_prep.stages.base import BackendContext
    from ga3ce_prep.stages.objects import MaskObjects, MaskParams

    class Fixed(MaskObjects):
        name = "fixed"

        @dataclass(frozen=True, kw_only=True)
        class Params(MaskParams):
            pass

        def masks(self, frame, depth):
            labels = np.full((8, 8), -1, np.int32)
            labels.flat[10:31] = 0
            return labels, None

    depth = np.full((8, 8), 5.0, np.float32)
    valid = np.zeros((8, 8), bool)
    depth.flat[10:20], valid.flat[10:20] = 2.0, True
    depth.flat[20:31] = 1.0
    K = np.array([[4.0, 0, 4.0], [0, 4.0, 4.0], [0, 0, 1]])
    frame = FrameRef("f", "test", "s", tmp_path / "x.png", K, (8, 8), np.zeros(4, np.float32))
    ctx = BackendContext(tmp_path)
    m = Fixed({}, ctx).objects(frame, DepthMap(depth, valid))
    c = Fixed({"median_pixels": "completed"}, ctx).objects(frame, DepthMap(depth, valid))
    assert m.xyz[0, 2] == 2.0 and c.xyz[0, 2] == 1.0
    # the measured pixels: columns 2..7 of row 1 and 0..3 of row 2 -> median u 3 at 2 m: (3 - 4) * 2 / 4
    assert m.xyz[0, 0] == pytest.approx(-0.5)
    np.testing.assert_allclose(m.score, 10 / 21)   # the measured fraction either way
    np.testing.assert_allclose(c.score, 10 / 21)
    assert (m.area[0], c.area[0]) == (21, 21)
    m11 = Fixed({"min_points": 11}, ctx).objects(frame, DepthMap(depth, valid))
    c11 = Fixed({"min_points": 11, "median_pixels": "completed"}, ctx).objects(frame, DepthMap(depth, valid))
    assert (len(m11.xyz), m11.n_dropped, len(c11.xyz), c11.n_dropped) == (0, 1, 1, 0)


def test_geometric_segments_name_their_plane_pieces():
    """A floor under a camera looking down at 45 degrees and a 30 cm box on it: the floor's pieces are
    planes, the box a cluster (GeometricSegments.plane)."""
    from ga3ce_prep.estimators.segment.geometric import GeometricParams, segment_geometric

    H, W, f = 120, 160, 120.0
    K = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]])
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    ray = np.stack([(u - W / 2) / f, (v - H / 2) / f, np.ones_like(u)], axis=-1)
    down = np.array([0.0, np.sqrt(0.5), np.sqrt(0.5)])        # the floor's normal points at the camera, 1.5 m away
    depth = (1.5 / (ray @ down)).astype(np.float32)
    box = (np.abs(u - W / 2) < 12) & (np.abs(v - H / 2) < 12)
    depth[box] -= 0.3                                          # a box standing 30 cm proud of the floor
    seg = segment_geometric(depth, K, GeometricParams(stride=2, drop_subject=False))
    floor, top = seg.labels[5, 5], seg.labels[H // 2, W // 2]
    assert floor >= 0 and top >= 0 and floor != top
    assert seg.plane[floor] and not seg.plane[top] and len(seg.plane) == seg.labels.max() + 1
