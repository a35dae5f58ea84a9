"""The synthetic world, read back through the real adapters: ids, geometry and splits agree with
the exact truth side-car (the adapters were written from the format notes, not from the writer)."""
import numpy as np
import pytest

from ga3ce_prep.datasets import open_dataset
from ga3ce_prep.frames import load_depth, load_rgb
from ga3ce_prep.geometry import angular_error_deg, project
from ga3ce_prep.synthetic import generate
from ga3ce_prep.synthetic.truth import TruthReader


@pytest.fixture(scope="module", params=["gfie", "cad120", "gafa"])
def world(request, tmp_path_factory):
    out = tmp_path_factory.mktemp(request.param)
    generate(request.param, out, scenes=3, frames_per_scene=4, seed=5, width=160, progress=False)
    return request.param, out, list(open_dataset(request.param, out).frames()), TruthReader(out / "truth.h5")


def test_every_frame_matches_the_truth(world):
    fmt, out, frames, truth = world
    assert sorted(f.id for f in frames) == sorted(truth.frame_ids)
    for f in frames:
        t = truth.get(f.id)
        np.testing.assert_allclose(f.K, t.K, rtol=1e-5)
        assert angular_error_deg(f.gaze, t.gaze) < 0.05
        origin = t.head_center if fmt == "gafa" else t.eye  # GAFA annotates the head position
        np.testing.assert_allclose(f.eye, origin, atol=1e-4)
        u, v = project(t.head_center, f.K)
        x1, y1, x2, y2 = f.head_box
        assert x1 - 2 <= u <= x2 + 2 and y1 - 2 <= v <= y2 + 2, f.id
        if fmt != "gafa":
            np.testing.assert_allclose(f.gaze_2d, project(t.gaze_target, f.K), atol=1.0)


def test_pixels_load_at_the_annotated_size(world):
    fmt, out, frames, truth = world
    f = frames[0]
    rgb = load_rgb(f.image_path)
    assert rgb.shape == (f.image_size[1], f.image_size[0], 3)
    if fmt == "gafa":
        assert f.depth_path is None
    else:
        d = load_depth(f.depth_path, f.depth_scale)
        exact = truth.get(f.id).depth
        both = (d > 0) & (exact > 0)
        assert both.mean() > 0.5  # holes exist but most pixels are measured
        assert np.median(np.abs(d[both] - exact[both])) < 0.02  # sensor noise, metres


def test_splits_by_scene(world):
    fmt, out, frames, truth = world
    scene_split = {}
    for f in frames:
        assert scene_split.setdefault(f.scene, f.split) == f.split
    # GAFA's val is the tail of the training sessions' 7-frame windows: 4 frames per camera hold none
    expected = {"test"} if fmt == "cad120" else {"train", "test"} if fmt == "gafa" else {"train", "val", "test"}
    assert set(scene_split.values()) == expected
