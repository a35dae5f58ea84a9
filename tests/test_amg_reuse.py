"""Segment-everything reuse across the frames of a camera sequence (`reuse: sequence`,
estimators/segment/reuse.py) on the synthetic world, with a scripted decoder whose masks are the
world's instance masks of each frame: where only the person moved, reuse gives the exact
generator's masks while decoding a fraction of the prompts."""
import dataclasses
from itertools import groupby

import numpy as np
import onnx
import pytest

from ga3ce_prep.datasets import open_dataset
from ga3ce_prep.estimators.segment.mobilesam import MobileSamSegmenter
from ga3ce_prep.estimators.segment.mobilesam_runners import SegmenterOptions
from ga3ce_prep.estimators.segment.reuse import FrameCues, ReuseParams, SequenceReuse, box_cells, mask_cells, to_cells
from ga3ce_prep.frames import load_rgb
from ga3ce_prep.synthetic.truth import TruthReader
from ga3ce_prep.testing import scripted

OPTIONS = SegmenterOptions(points_per_side=16, decoder_mode="official", threads=1)
# the scripted decoder's masks are exact and so is the truth depth: any sliver that moved counts; at 160x120 a cell of
# the pooling encoder averages 2.5x2.5 pixels, whose sensor noise moves it by up to 0.2 of the mean norm
PARAMS = ReuseParams(reuse="sequence", reuse_depth_change=1e-3, reuse_embedding_change=0.3)


@pytest.fixture(scope="module")
def world(synth_world, tmp_path_factory):
    """(segmenter with the scripted label decoder, the decoder, frames grouped by sequence, truth)."""
    d = tmp_path_factory.mktemp("reuse_models")
    truth = TruthReader(synth_world / "truth.h5")
    frames = list(open_dataset("gfie", synth_world))
    labels0 = truth.instance(frames[0].id).astype(np.int64) + 1
    onnx.save(scripted.pooling_encoder("normalised"), d / "enc.onnx")
    onnx.save(scripted.scripted_decoder(labels0), d / "dec.onnx")
    seg = MobileSamSegmenter(d / "enc.onnx", d / "dec.onnx", OPTIONS)
    seg.decoder = dec = scripted.LabelDecoder(labels0)
    seqs = [sorted(g, key=lambda f: f.index) for _, g in groupby(sorted(frames, key=lambda f: f.sequence),
                                                                    key=lambda f: f.sequence)]
    return seg, dec, seqs, truth


def run(seg, dec, frames, truth, reuse: SequenceReuse):
    """Per frame: (exact Segmentation, reuse Segmentation, prompts the reuse run decoded)."""
    out = []
    for f in frames:
        dec.labels = truth.instance(f.id).astype(np.int64) + 1
        rgb = load_rgb(f.image_path)
        exact = seg.segment(rgb)
        boxes = np.stack([f.head_box, truth.get(f.id, maps=False).body_box])      # the person: head, body
        reuse.start(FrameCues(f.index, rgb.shape[:2], depth=truth.depth(f.id), boxes=boxes))
        calls = dec.calls
        r = seg.segment(rgb, reuse=reuse)
        out.append((exact, r, dec.calls - calls))
    return out


def test_reuse_gives_the_exact_masks_where_only_the_person_moves(world):
    seg, dec, seqs, truth = world
    n_key = n_reuse = 0
    for frames in seqs:
        assert len(frames) == 4
        for i, (exact, r, calls) in enumerate(run(seg, dec, frames, truth, SequenceReuse(PARAMS))):
            assert len(r.masks) == len(exact.masks) > 3
            np.testing.assert_array_equal(r.masks, exact.masks)
            np.testing.assert_array_equal(r.scores, exact.scores)
            np.testing.assert_array_equal(r.boxes, exact.boxes)
            assert r.reuse.key == (i == 0) and r.n_prompts == calls
            if i == 0:
                assert r.reuse.reason == "first" and calls == 256
                n_key += 1
            else:
                assert r.reuse.reason == "" and 0 < calls < 128 and r.reuse.decoded_share == calls / 256
                n_reuse += 1
    assert (n_key, n_reuse) == (3, 9)


def test_a_gap_in_frame_numbers_forces_a_key_frame(world):
    seg, dec, seqs, truth = world
    frames = [seqs[0][0], seqs[0][1], seqs[0][3]]                  # raw numbers n, n+1, n+3
    steps = [r.reuse for exact, r, _ in run(seg, dec, frames, truth, SequenceReuse(PARAMS))]
    assert [(s.key, s.reason) for s in steps] == [(True, "first"), (False, ""), (True, "gap")]
    assert steps[2].decoded_share == 1.0


def test_age_and_changed_share_force_key_frames(world):
    seg, dec, seqs, truth = world
    aged = SequenceReuse(ReuseParams(reuse="sequence", reuse_max_age=2))
    assert [r.reuse.reason for _, r, _ in run(seg, dec, seqs[1], truth, aged)] == ["first", "", "age", ""]
    everything = SequenceReuse(ReuseParams(reuse="sequence", reuse_embedding_change=0.0, reuse_max_changed=0.9))
    assert [r.reuse.reason for _, r, _ in run(seg, dec, seqs[1][:2], truth, everything)] == ["first", "changed"]


def test_cells_of_maps_boxes_and_masks():
    # 640x480 -> 1024x768: 1.6 input pixels per image pixel, 10 image pixels per 16-pixel cell
    v = np.zeros((480, 640), np.float32)
    v[:20, :40] = 1.0                                                 # cells rows 0-1, columns 0-3
    cells = to_cells(v, (480, 640))
    assert cells[:1, :3].min() > 0.97 and cells[1, 3] > 0.9           # bilinear: the edges blur a little
    assert cells[3:].max() == 0.0 and cells[:, 5:].max() == 0.0       # rows 48.. are padding
    b = box_cells(np.array([[20.0, 10.0, 29.0, 19.0], [np.nan] * 4]), (480, 640), margin=1)
    assert np.array_equal(np.argwhere(b)[[0, -1]], [[0, 1], [2, 3]])  # cells (1, 2) grown by one
    low = np.full((1, 256, 256), -1.0, np.float32)
    low[0, 5, 9] = 1.0
    assert np.array_equal(np.argwhere(mask_cells(low)[0]), [[1, 2]])


@pytest.mark.parametrize("threshold", [0.96, 0.98])
def test_candidates_near_a_threshold_are_decoded_on_every_frame(world, threshold):
    # the scripted objects' best candidate predicts IoU 0.97: 0.01 above a 0.96 threshold (each wins NMS), 0.01
    # below 0.98 (each would win NMS if it passed); either way sensor noise could flip it, so its prompt is decoded
    # every frame
    seg, dec, seqs, truth = world
    base = seg.options
    reference = SequenceReuse(PARAMS)
    run(seg, dec, seqs[0][:1], truth, reference)                  # the default threshold 0.88: nothing near
    assert len(reference.key.won) > 3 and len(reference.key.near) == 0
    seg.options = dataclasses.replace(base, pred_iou_thresh=threshold)
    try:
        reuse, plans = SequenceReuse(PARAMS), []
        plan = reuse.plan
        reuse.plan = lambda emb, prompts: plans.append(plan(emb, prompts)) or plans[-1]
        out = run(seg, dec, seqs[0], truth, reuse)
    finally:
        seg.options = base
    assert np.array_equal(np.sort(reuse.key.near), np.sort(reference.key.won))
    for i, (exact, r, _calls) in enumerate(out):
        np.testing.assert_array_equal(r.masks, exact.masks)
        assert len(exact.masks) == (len(reference.key.won) if threshold < 0.97 else 0)
        if i:
            assert not r.reuse.key and plans[i][1][reuse.key.near].all()
