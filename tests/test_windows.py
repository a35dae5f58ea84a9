"""Temporal windows (`Backend.window`, `frames.frame_windows`): which neighbours a frame gets (gaps,
sequence ends, the cyclic previous frame), windows that reach into other shards, cache keys that
follow the neighbours, and a windowed stage's store independent of the shard size."""
import os
from pathlib import Path

import numpy as np
import pytest

from ga3ce_prep.datasets import open_dataset
from ga3ce_prep.frames import FrameRef, frame_windows
from ga3ce_prep.pipeline import run_pipeline, tasks
from ga3ce_prep.pipeline.config import load_pipeline
from ga3ce_prep.pipeline.run import _make_shards
from ga3ce_prep.stages import BACKENDS, call_backend
from ga3ce_prep.stages.view import OracleView
from ga3ce_prep.store import open_store
from ga3ce_prep.testing.worlds import GAFA_GAP


def _frame(seq: str, index: int) -> FrameRef:
    return FrameRef(id=f"{seq}/{index}", split="test", scene="s", image_path=Path("x.jpg"), K=np.eye(3),
                    image_size=(4, 3), head_box=np.zeros(4, np.float32), sequence=seq, index=index)


def _numbers(w) -> list:
    return [None if f is None else (f.sequence, f.index) for f in w.frames]


def test_window_rule_on_frame_numbers_with_gaps_and_ends():
    a = [0, 1, 2, 3, 4, 5, 6, 7, 9, 10, 11, 12, 13, 14, 15, 20]  # raw numbers: 8 and 16-19 missing
    frames = [_frame("A", i) for i in a] + [_frame("B", i) for i in (6, 4, 5, 3)] + [_frame("", 0), _frame("", 0)]
    w = dict(zip((f.id for f in frames[:len(a) + 4]), frame_windows(frames, 7)))

    def A(*ns):
        return [None if n is None else ("A", n) for n in ns]

    # inside a run of 7: the 7 consecutive numbers; previous = the frame before the window
    assert _numbers(w["A/4"]) == A(1, 2, 3, 4, 5, 6, 7) and w["A/4"].complete
    assert w["A/4"].previous.index == 0
    # the window starting the sequence: previous is cyclic, the sequence's last frame (np.roll)
    assert _numbers(w["A/3"]) == A(0, 1, 2, 3, 4, 5, 6) and w["A/3"].previous.index == 20
    # at a gap: None where the number is missing, the window is incomplete
    assert _numbers(w["A/7"]) == A(4, 5, 6, 7, None, 9, 10) and not w["A/7"].complete
    assert _numbers(w["A/10"]) == A(7, None, 9, 10, 11, 12, 13)
    # after the gap: previous is the frame before the window whatever its number (across the gap)
    assert _numbers(w["A/12"]) == A(9, 10, 11, 12, 13, 14, 15) and w["A/12"].previous.index == 7
    # sequence ends: nothing before 0, nothing after the last frame
    assert _numbers(w["A/0"]) == A(None, None, None, 0, 1, 2, 3)
    assert _numbers(w["A/15"]) == A(12, 13, 14, 15, None, None, None)
    assert _numbers(w["A/20"]) == A(None, None, None, 20, None, None, None) and w["A/20"].previous.index == 15
    # another sequence never lends frames; the adapter's order within a sequence does not matter
    assert _numbers(w["B/4"]) == [None, None, ("B", 3), ("B", 4), ("B", 5), ("B", 6), None]
    assert w["B/4"].previous.index == 6
    # a frame without a sequence is alone (GFIE's frames all have index 0)
    lone = frame_windows(frames, 7)[-1]
    assert [f is frames[-1] for f in lone.frames] == [False] * 3 + [True] + [False] * 3
    assert lone.frames[2] is None and lone.previous is frames[-1]
    # size 1 is the frame itself; an even size and a repeated number are refused
    assert [_numbers(x) for x in frame_windows(frames[:2], 1)] == [[("A", 0)], [("A", 1)]]
    with pytest.raises(ValueError, match="odd"):
        frame_windows(frames, 4)
    with pytest.raises(ValueError, match="raw frame number 3"):
        frame_windows([_frame("A", 3), _frame("A", 3)], 3)


class WindowProbe(OracleView):
    """A windowed view backend whose v records what it was given: (present neighbours, previous
    frame's raw number + 1, 1000 + the sum of the present neighbours' numbers)."""

    window = 5

    def view(self, frame, window):
        assert window.frames[2] is frame
        present = [f.index for f in window.frames if f is not None]
        assert all(f.sequence == frame.sequence for f in window.frames if f is not None)
        return np.float32([len(present), window.previous.index + 1, 1000 + sum(present)])


def _expected_probe(frames):
    """What WindowProbe returns for each frame, from the frames by hand: neighbours within 2 raw
    numbers in the same sequence; previous = the latest frame numbered below index - 2, else the
    sequence's last."""
    out = {}
    for f in frames:
        seq = sorted(g.index for g in frames if g.sequence == f.sequence)
        near = [n for n in seq if abs(n - f.index) <= 2]
        before = [n for n in seq if n < f.index - 2]
        out[f.id] = [len(near), (before[-1] if before else seq[-1]) + 1, 1000 + sum(near)]
    return out


def _pipeline(view: dict, shard_size: int) -> dict:
    return {"name": "gafa-windows", "dataset": {"format": "gafa"},
            "stages": {"depth": {"backend": "oracle"}, "objects": {"backend": "oracle"}, "head": {"backend": "depth"},
                       "pose": {"backend": "oracle"}, "view": view}, "run": {"shard_size": shard_size}}


@pytest.fixture
def probe(monkeypatch):
    """view/oracle replaced by WindowProbe for the test (and no backend instance kept after it)."""
    monkeypatch.setitem(BACKENDS, "view/oracle", f"{__name__}:WindowProbe")
    monkeypatch.setattr(tasks, "_backends", {})
    return _pipeline({"backend": "oracle"}, 3)


def test_windows_reach_across_shards_and_the_store_does_not_depend_on_the_shard_size(
        probe, synth_gafa_world, tmp_path):
    frames = list(open_dataset("gafa", synth_gafa_world).frames())
    assert (GAFA_GAP[0], GAFA_GAP[1]) not in {(f.sequence, f.index) for f in frames}
    conf = load_pipeline(probe, synth_gafa_world)
    shards = _make_shards(conf, frames, synth_gafa_world)
    assert [len(s.windows["view"]) for s in shards] == [len(s.frames) for s in shards]
    assert set(shards[0].windows) == {"view"}
    # frame 1 of shard 1 is raw frame 4 of the first sequence: its window holds raw frames 2-6,
    # of which 2 sits in shard 0 and 6 in shard 2
    w = shards[1].windows["view"][1]
    assert [f.index for f in w.frames] == [2, 3, 4, 5, 6]
    assert w.frames[0] is shards[0].frames[2] and w.frames[4] is shards[2].frames[0]
    stores = {}
    for size in (3, 7):
        out = tmp_path / f"s{size}.zarr"
        run_pipeline({**probe, "run": {"shard_size": size}}, synth_gafa_world, out, progress=False)
        stores[size] = open_store(out)
    s3, s7 = stores[3], stores[7]
    assert len(s3) == len(frames)
    expected = _expected_probe(frames)
    for fid, v in zip(s3.frames["id"], s3.frames["view"]):
        np.testing.assert_array_equal(v, expected[fid], err_msg=fid)
    for name in s3.frames:
        np.testing.assert_array_equal(s3.frames[name], s7.frames[name], err_msg=name)


def test_a_windowed_stage_key_follows_its_neighbours_only(probe, synth_gafa_world):
    frames = list(open_dataset("gafa", synth_gafa_world).frames())
    conf = load_pipeline(probe, synth_gafa_world)
    before = _make_shards(conf, frames, synth_gafa_world)
    # raw frame 3 of the first sequence (shard 1) lies in the windows of raw frames 1-5 (shards 0
    # and 1) and is the previous frame of raw frame 6's window (shard 2); change its file's identity
    f = frames[3]
    assert (f.index, before[1].frames[0]) == (3, f)
    st = os.stat(f.image_path)
    os.utime(f.image_path, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))
    try:
        after = _make_shards(conf, frames, synth_gafa_world)
    finally:
        os.utime(f.image_path, ns=(st.st_atime_ns, st.st_mtime_ns))
    changed = {(i, stage) for i, (a, b) in enumerate(zip(before, after))
               for stage in a.keys if a.keys[stage] != b.keys[stage]}
    # shards 0 and 2: only the view, which read the frame as a neighbour; shard 1: everything (its
    # own frame); every later shard: nothing
    assert {st for i, st in changed if i in (0, 2)} == {"view"}
    assert {(i, st) for i, st in changed if i == 2} == {(2, "view")}
    assert {st for i, st in changed if i == 1} == set(before[1].keys)
    assert not {i for i, _ in changed} - {0, 1, 2}


def test_a_windowed_stage_keeps_the_other_stages_keys(probe, synth_gafa_world):
    """The window enters the windowed stage's key only: the other stages' keys are those of the
    same pipeline with an unwindowed view backend."""
    frames = list(open_dataset("gafa", synth_gafa_world).frames())
    conf = load_pipeline(probe, synth_gafa_world)
    windowed = _make_shards(conf, frames, synth_gafa_world)
    BACKENDS["view/oracle"] = "ga3ce_prep.stages.view:OracleView"  # restored by the fixture
    plain = _make_shards(conf, frames, synth_gafa_world)
    assert not plain[0].windows
    for a, b in zip(windowed, plain):
        assert {k: v for k, v in a.keys.items() if k != "view"} == {k: v for k, v in b.keys.items() if k != "view"}
        assert a.keys["view"] != b.keys["view"]


def test_a_windowed_backend_called_without_a_window_gets_the_frame_alone(probe, synth_gafa_world):
    """`predict` calls backends one frame at a time: a windowed one sees no neighbours."""
    conf = load_pipeline(probe, synth_gafa_world)
    f = next(iter(open_dataset("gafa", synth_gafa_world).frames()))
    v = call_backend(conf.stages["view"].make(synth_gafa_world), f, {})
    np.testing.assert_array_equal(v, [1, f.index + 1, 1000 + f.index])
