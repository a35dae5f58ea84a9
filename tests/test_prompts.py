"""The generator's prompts (estimators/segment/prompts.py): point and box prompts' decoder inputs,
the generator on them with the random-weight MobileSAM, the grid left as it was, and reuse over
prompts that move from frame to frame."""
import numpy as np
import pytest

from ga3ce_prep.errors import ConfigError
from ga3ce_prep.estimators.segment import amg
from ga3ce_prep.estimators.segment.mobilesam import MobileSamSegmenter
from ga3ce_prep.estimators.segment.mobilesam_runners import SegmenterOptions
from ga3ce_prep.estimators.segment.prompts import Prompts
from ga3ce_prep.estimators.segment.reuse import GRID, FrameCues, ReuseParams, SequenceReuse, prompt_reaches
from ga3ce_prep.testing import mobilesam_random
from ga3ce_prep.testing.scripted import drawn_frame

ENC, DEC = mobilesam_random.ensure()
# random weights: permissive thresholds keep candidates (tests/test_mobilesam_torch.py's)
MANY = dict(points_per_side=5, pred_iou_thresh=0.0, stability_score_thresh=0.3, stability_score_offset=0.05,
            box_nms_thresh=1.0, threads=1)


def test_prompts_decoder_inputs_by_kind():
    p = Prompts.at([[10.0, 20.0], [30.0, 40.0]]).cat(Prompts(np.array([[5.0, 6.0]]), np.array([[1.0, 2.0, 9.0, 8.0]])))
    assert p.boxed.tolist() == [False, False, True]
    assert [b.tolist() for b in p.batches(np.arange(3), 1)] == [[0], [1], [2]]
    assert [b.tolist() for b in p.batches(np.array([2, 1, 0]), None)] == [[1, 0], [2]]
    coords, labels = p.filter(slice(0, 2)).decoder_inputs((480, 640))
    assert coords.shape == (2, 2, 2) and labels.tolist() == [[1, -1], [1, -1]]
    np.testing.assert_allclose(coords[0, 0], np.array([10, 20]) * 1.6)
    coords, labels = p.filter([2]).decoder_inputs((480, 640))
    assert labels.tolist() == [[1, 2, 3]]
    np.testing.assert_allclose(coords[0], np.array([[5, 6], [1, 2], [9, 8]]) * 1.6)
    with pytest.raises(ValueError, match="one kind"):
        p.decoder_inputs((480, 640))


@pytest.fixture(scope="module")
def segmenter():
    return MobileSamSegmenter(ENC, DEC, SegmenterOptions(**MANY))


def test_the_grid_given_as_prompts_is_the_grid(segmenter):
    """The default grid and the same grid given as point prompts: the same masks, bit for bit (the grid
    path is the exact generator's, tests/test_mobilesam_models.py checks it against the reference's)."""
    rgb = drawn_frame()
    a = segmenter.segment(rgb)
    b = segmenter.segment(rgb, prompts=Prompts.grid(amg.build_point_grid(5), rgb.shape[:2]))
    assert a.n_prompts == b.n_prompts == 25 and len(a.masks) > 5
    for k in ("masks", "scores", "stability", "boxes", "points"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))


def test_box_prompts_are_decoded_with_their_click_and_corners():
    """A batch of box prompts goes to the decoder as (click, corners); each gives the decoder's
    multimask candidates, as a point does (no stability filter: random weights' box masks fail it)."""
    segmenter = MobileSamSegmenter(ENC, DEC, SegmenterOptions(**{**MANY, "stability_score_thresh": 0.0}))
    rgb = drawn_frame()
    boxes = np.array([[100.0, 80.0, 300.0, 260.0], [350.0, 200.0, 600.0, 470.0]])
    prompts = Prompts.at([[50.0, 400.0]]).cat(Prompts(0.5 * (boxes[:, :2] + boxes[:, 2:]), boxes))
    r = segmenter.segment(rgb, prompts=prompts)
    assert r.n_prompts == 3 and r.n_candidates == len(r.masks) == 3 * 3
    dec = segmenter.decoder
    dec.set_image(segmenter.encoder.embed(rgb))
    iou, _ = dec.predict_iou(*prompts.filter([1, 2]).decoder_inputs(rgb.shape[:2]))
    box_rows = np.flatnonzero(np.all(r.points[:, None] == prompts.points[1:], axis=-1).any(axis=1))
    assert len(box_rows) == 6
    np.testing.assert_allclose(np.sort(r.scores[box_rows]), np.sort(iou[:, 1:].ravel()), atol=1e-6)
    # the same clicks without their boxes predict other IoUs
    point_iou, _ = dec.predict_iou(*Prompts.at(prompts.points[1:]).decoder_inputs(rgb.shape[:2]))
    assert np.abs(point_iou - iou).max() > 1e-3


def test_prompts_need_the_full_image_crop_alone():
    seg = MobileSamSegmenter(ENC, DEC, SegmenterOptions(**{**MANY, "crop_n_layers": 1}), verify=False)
    with pytest.raises(ConfigError, match="crop_n_layers 0"):
        seg.segment(drawn_frame(), prompts=Prompts.at([[1.0, 1.0]]))


def test_a_box_prompt_reaches_every_cell_of_its_box():
    cells = np.zeros((GRID, GRID), bool)
    cells[10, 20] = True                     # the cell of 1024-frame pixels x 320..335, y 160..175
    hw = (480, 640)                          # 1.6 input pixels per image pixel
    p = Prompts.at([[205.0, 105.0], [0.0, 0.0]]).cat(
        Prompts(np.array([[0.0, 0.0], [0.0, 0.0]]), np.array([[150.0, 50.0, 210.0, 120.0], [0.0, 0.0, 190.0, 90.0]])))
    assert prompt_reaches(p, cells, hw).tolist() == [True, False, True, False]


def test_reuse_keeps_the_key_frames_prompts_and_adds_new_ones_where_cells_changed():
    """A reuse frame's prompts: the key frame's, then this frame's that the key lacks and that reach a
    changed cell (the grid's are the key's: nothing added)."""
    hw = (480, 640)
    reuse = SequenceReuse(ReuseParams(reuse="sequence", reuse_max_changed=1.0))
    key = Prompts.at([[100.0, 100.0], [500.0, 300.0]]).cat(
        Prompts(np.array([[300.0, 200.0]]), np.array([[280.0, 180.0, 320.0, 220.0]])))
    emb = np.ones((1, 256, 64, 64), np.float32)
    reuse.start(FrameCues(0, hw))
    planned, decode = reuse.plan(emb, key)
    assert planned is key and decode is None
    reuse.merge(amg.MaskRecords.empty(), SegmenterOptions())
    reuse.settle(np.zeros(0, np.int64))
    # next frame: the embedding changed around (500, 300) only; the box moved a pixel (sensor noise)
    moved = Prompts(np.array([[301.0, 200.0], [498.0, 298.0]]), np.array([[281.0, 180.0, 321.0, 220.0],
                                                                        [480.0, 280.0, 520.0, 320.0]]))
    frame = Prompts.at([[100.0, 100.0], [500.0, 300.0]]).cat(moved)
    emb2 = emb.copy()
    emb2[0, :, 29:31, 49:51] = 5.0                                   # cells around (500, 300) * 1.6 / 16
    reuse.start(FrameCues(1, hw))
    planned, decode = reuse.plan(emb2, frame)
    assert len(planned) == 4                                         # the key's three, the new box near the change
    np.testing.assert_array_equal(planned.points[:3], key.points)
    np.testing.assert_array_equal(planned.boxes[3], moved.boxes[1])
    assert decode.tolist() == [False, True, False, True] and not reuse.last.key
