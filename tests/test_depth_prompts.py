"""Segment-everything prompted by depth (`prompts: depth`): the prompt rule
(estimators/segment/depth_prompts.py) on hand-made segments."""
import numpy as np

from ga3ce_prep.estimators.segment import amg
from ga3ce_prep.estimators.segment.depth_prompts import DepthPromptParams, depth_prompts, segment_boxes
from ga3ce_prep.estimators.segment.geometric import GeometricSegments


def hand_made_segments() -> GeometricSegments:
    """(240, 320) labels: 0 an L-shaped plane piece (its centroid off it), 1 a rectangle cluster."""
    labels = np.full((240, 320), -1, np.int32)
    labels[100:200, 20:40] = 0            # the L's upright
    labels[180:200, 40:120] = 0           # its foot
    labels[50:80, 200:260] = 1
    return GeometricSegments(labels, np.array([True, False]))


def test_segment_boxes_and_clicks_on_the_segment():
    seg = hand_made_segments()
    boxes, clicks = segment_boxes(seg.labels)
    np.testing.assert_array_equal(boxes, [[20, 100, 119, 199], [200, 50, 259, 79]])
    # the L's centroid (51.7, 167.3) is off the L: its click is the L's pixel nearest it
    x, y = clicks[0].astype(int)
    assert seg.labels[y, x] == 0 and (x, y) == (39, 167)
    np.testing.assert_array_equal(clicks[1], [229, 64])   # the rectangle's: a centre pixel (ties: the first)
    assert [len(a) for a in segment_boxes(np.full((4, 4), -1))] == [0, 0]


def grid_points(side: int, hw=(480, 640)) -> np.ndarray:
    return amg.build_point_grid(side) * [hw[1], hw[0]]


def test_a_click_per_segment_and_the_grid_points_on_clusters_in_image_pixels():
    """Labels at half the image's resolution: a label pixel x covers image pixels 2x and 2x + 1."""
    seg = hand_made_segments()
    p = depth_prompts(seg, (480, 640), DepthPromptParams(prompts="depth", prompt_grid=8))
    assert not p.boxed.any()
    np.testing.assert_array_equal(p.points[:2], [[78.5, 334.5], [458.5, 128.5]])   # the clicks, at pixel centres
    g = grid_points(8)
    on_cluster = (g[:, 0] >= 400) & (g[:, 0] < 520) & (g[:, 1] >= 100) & (g[:, 1] < 160)
    assert on_cluster.sum() == 1                         # (440, 150) on the cluster; none on the plane piece
    np.testing.assert_array_equal(p.points[2:], g[on_cluster])
    none = depth_prompts(seg, (480, 640), DepthPromptParams(prompts="depth", prompt_grid=0))
    assert len(none) == 2


def test_boxes_and_the_sparse_grid_on_request():
    seg = hand_made_segments()
    p = depth_prompts(seg, (480, 640), DepthPromptParams(prompts="depth", prompt_grid=0, prompt_boxes=True,
                                                         prompt_sparse_grid=8))
    np.testing.assert_array_equal(p.boxes[:2], [[40, 200, 239, 399], [400, 100, 519, 159]])
    np.testing.assert_array_equal(p.points[:2], [[78.5, 334.5], [458.5, 128.5]])
    g = grid_points(8)
    labels = seg.labels[(g[:, 1] / 2).astype(int), (g[:, 0] / 2).astype(int)]
    assert (labels >= 0).sum() == 4 + 2 + 1               # on the L's upright, its foot, the cluster
    assert p.boxed.tolist() == [True, True] + [False] * (64 - 7)
    np.testing.assert_array_equal(p.points[2:], g[labels < 0])
