"""The automatic mask generator's grid, crops and filters against hand-computed cases, and the mask
postprocessing against torch's F.interpolate (the reference's postprocess_masks)."""
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from ga3ce_prep.errors import ConfigError
from ga3ce_prep.estimators.segment import amg


def test_point_grid_is_cell_centres_x_fastest():
    g = amg.build_point_grid(2)
    np.testing.assert_allclose(g, [[0.25, 0.25], [0.75, 0.25], [0.25, 0.75], [0.75, 0.75]])
    assert amg.build_point_grid(32).shape == (1024, 2)
    assert [len(x) for x in amg.layer_point_grids(32, 2, 2)] == [1024, 256, 64]


def test_crop_boxes_by_hand():
    boxes, layers = amg.crop_boxes((480, 640), 1, 512 / 1500)
    # overlap = int(0.3413 * 480 * 2/2) = 163; w = ceil((163 + 640)/2) = 402; h = ceil((163 + 480)/2) = 322
    assert boxes[0] == [0, 0, 640, 480] and layers == [0, 1, 1, 1, 1]
    assert boxes[1:] == [[0, 0, 402, 322], [0, 159, 402, 480], [239, 0, 640, 322], [239, 159, 640, 480]]


def test_stability_score_formula():
    logits = np.array([[[2.0, 0.5, -0.5, -2.0], [1.5, 0.9, -0.9, -3.0]]], np.float32)  # (1, 2, 4)
    # > +1: 2 pixels (2.0, 1.5); > -1: 6 pixels (all but -2.0, -3.0)
    assert amg.stability_score(logits, 1.0)[0] == pytest.approx(2 / 6)
    assert amg.stability_score(logits, 0.6)[0] == pytest.approx(3 / 5)  # > 0.6: 2.0 1.5 0.9; > -0.6: and 0.5 -0.5
    assert np.isnan(amg.stability_score(np.full((1, 2, 2), -5.0, np.float32), 1.0)[0])


def test_masks_to_boxes_inclusive_and_empty():
    m = np.zeros((2, 5, 6), bool)
    m[0, 1:4, 2:5] = True
    assert amg.masks_to_boxes(m).tolist() == [[2, 1, 4, 3], [0, 0, 0, 0]]


def test_box_nms_greedy_threshold_and_stable_ties():
    boxes = np.array([[0, 0, 10, 10], [0, 0, 10, 9], [0, 0, 10, 5], [20, 20, 30, 30]])
    scores = np.array([0.9, 0.95, 0.8, 0.9])
    # IoU(b1, b0) = 90/100 > 0.7: b0 suppressed by b1; IoU(b1, b2) = 50/90 = 0.56 kept; b3 disjoint
    assert amg.box_nms(boxes, scores, 0.7).tolist() == [1, 3, 2]
    # equal scores: the earlier box wins (torchvision's stable sort)
    assert amg.box_nms(boxes[:2], np.array([0.5, 0.5]), 0.7).tolist() == [0]
    assert amg.box_nms(boxes, scores, 1.0).tolist() == [1, 0, 3, 2]


def test_near_crop_edge_ignores_image_edges():
    crop = [100, 0, 300, 200]
    boxes = np.array([[5, 50, 50, 100],     # x1 = 105 in the image: within 20 px of the crop's left edge
                      [50, 0, 80, 100],     # touches the top, which is also the image's top edge
                      [50, 50, 150, 150]])  # inside
    assert amg.near_crop_edge(boxes, crop, [0, 0, 300, 200]).tolist() == [True, False, False]


def test_remove_small_regions_holes_and_islands():
    m = np.zeros((20, 20), bool)
    m[2:12, 2:12] = True
    m[5, 5] = False                 # 1-pixel hole
    m[16:18, 16:18] = True          # 4-pixel island
    filled, changed = amg.remove_small_regions(m, 5, "holes")
    assert changed and filled[5, 5] and filled.sum() == 100 + 4
    cleaned, changed = amg.remove_small_regions(filled, 5, "islands")
    assert changed and cleaned.sum() == 100 and not cleaned[16, 16]
    same, changed = amg.remove_small_regions(cleaned, 5, "islands")
    assert not changed and same.sum() == 100


def _torch_postprocess(low, orig_hw):
    """segment-anything's Sam.postprocess_masks on low-res logits."""
    newh, neww = amg.preprocess_shape(*orig_hw)
    x = F.interpolate(torch.from_numpy(low)[None], (1024, 1024), mode="bilinear", align_corners=False)
    x = x[..., :newh, :neww]
    return F.interpolate(x, orig_hw, mode="bilinear", align_corners=False)[0].numpy()


@pytest.mark.parametrize("orig_hw", [(480, 640), (720, 405), (333, 333)])
def test_upscale_logits_equals_reference_postprocessing(orig_hw):
    low = np.random.default_rng(0).standard_normal((3, 256, 256)).astype(np.float32)
    # OpenCV's bilinear weights are float32: within 1e-4 of torch (ONNX Runtime's Resize in the official
    # export is 6e-5 away from torch as well)
    np.testing.assert_allclose(amg.upscale_logits(low, orig_hw), _torch_postprocess(low, orig_hw), atol=1e-4)


def test_preprocess_shape_rounding():
    assert amg.preprocess_shape(480, 640) == (768, 1024)
    assert amg.preprocess_shape(1080, 1920) == (576, 1024)
    assert amg.preprocess_shape(401, 1000) == (411, 1024)  # 410.62 rounds up


def test_options_validate():
    with pytest.raises(ConfigError, match="box_nms_thresh"):
        amg.AmgOptions(box_nms_thresh=1.5)
    assert amg.AmgOptions().to_dict()["pred_iou_thresh"] == 0.88


def test_mask_records_filter_and_cat_keep_rows_aligned():
    def records(iou, crop):
        n = len(iou)
        return amg.MaskRecords(iou=np.array(iou, np.float32), stability=np.arange(n, dtype=np.float32) + 10 * crop,
                               box=np.arange(4 * n).reshape(n, 4) + 100 * crop, point=np.zeros((n, 2)),
                               low_res=np.zeros((n, amg.LOW_RES, amg.LOW_RES), np.float32),
                               crop_index=np.full(n, crop), prompt=np.arange(n))
    both = records([0.9, 0.8, 0.7], 0).cat(records([0.6], 1))
    assert both.crop_index.tolist() == [0, 0, 0, 1]
    picked = both.filter(np.array([3, 0]))                    # indices, in the order given
    np.testing.assert_array_equal(picked.iou, np.array([0.6, 0.9], np.float32))
    assert picked.box[:, 0].tolist() == [100, 0]
    assert picked.stability.tolist() == [10, 0]
    kept = both.filter(both.iou > 0.75)
    assert kept.stability.tolist() == [0, 1]
    assert kept.low_res.shape == (2, 256, 256)
    assert len(amg.MaskRecords.empty().cat(both)) == 4
    assert len(both.filter(slice(0, 0))) == 0
