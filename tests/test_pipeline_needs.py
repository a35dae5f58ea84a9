"""Backends that read another stage's output (`Backend.needs`) and record the source of each
frame's result (`Backend.sources`): the face-mesh view falling back to the pose, end to end."""
from pathlib import Path

import numpy as np

from ga3ce_prep.pipeline import load_pipeline, run_pipeline
from ga3ce_prep.pipeline.tasks import task_stages, task_upstream
from ga3ce_prep.skeleton import head_direction_from_pose
from ga3ce_prep.store import open_store
from ga3ce_prep.testing.worlds import SMALL

FACEMESH = [*SMALL, "stages.view.backend=facemesh", "stages.view.params={}", "run.shard_size=5"]


def test_a_view_that_reads_the_pose_waits_for_it(tmp_path):
    conf = load_pipeline("synthetic", tmp_path, overrides=FACEMESH, check_files=False)
    assert conf.upstream["view"] == ("input", "pose")
    assert task_stages(conf.upstream) == {"input": ("input",), "pose": ("pose",),
                                          "geometry": ("depth", "objects", "head"), "view": ("view",)}
    assert task_upstream(conf.upstream)["view"] == ("input", "pose")


def test_facemesh_view_falls_back_to_the_pose_and_the_store_says_so(synth_world, tmp_path):
    """The synthetic heads are shaded ellipsoids, so no face is found: every frame's v is the
    oracle pose's head direction, recorded as source "pose"; a changed pose recomputes the view."""
    out = tmp_path / "s.zarr"
    summary = run_pipeline("synthetic", synth_world, out, overrides=FACEMESH, progress=False)
    assert summary.counts.frames_kept == 12
    s = open_store(out)
    names = list(np.asarray(s.frames["view_source"]))
    assert names == [1] * 12
    import zarr
    assert zarr.open_group(str(out), mode="r")["frames/view_source"].attrs["names"] == ["face", "pose"]
    expected, ok = head_direction_from_pose(s.frames["pose"].astype(np.float64), np.full((12, 3), np.nan))
    assert ok.all()
    np.testing.assert_allclose(s.frames["view"], expected, atol=1e-6)
    # the view's cache key depends on the pose's: new pose noise, new views
    again = run_pipeline("synthetic", synth_world, out, progress=False,
                         overrides=[*FACEMESH, "stages.pose.params.seed=7"])
    assert again.computed_shards["pose"] == again.computed_shards["view"] == again.n_shards
    assert again.computed_shards["depth"] == 0
    s2 = open_store(out)
    assert not np.allclose(s2.frames["view"], s.frames["view"])


def test_a_batch_that_raises_is_retried_frame_by_frame():
    """StageEntry.attempt_batch: one frame that breaks its batch's call fails alone; a per-frame
    exception in the batch's results is that frame's failure record."""
    from ga3ce_prep.errors import FrameError
    from ga3ce_prep.frames import FrameRef
    from ga3ce_prep.pipeline.tasks import Shard, new_entry

    frames = [FrameRef(id=n, split="test", scene="s", image_path=Path(f"{n}.jpg"), K=np.eye(3), image_size=(4, 4),
                       head_box=np.zeros(4, np.float32)) for n in "abcd"]
    entry = new_entry("view", Shard(0, frames))

    def views(fs):
        if any(f.id == "b" for f in fs):
            raise FrameError("b is broken")
        return [FrameError("d has no face") if f.id == "d" else np.array([0, 0, -1.0], np.float32) for f in fs]

    entry.attempt_batch([0, 1, 2, 3], views, frames, {})
    assert entry.mask.tolist() == [True, False, True, False]
    assert entry.fail_idx == [1, 3]
    assert entry.fail_message == ["b is broken", "d has no face"]
    np.testing.assert_array_equal(entry.columns["view"][[0, 2]], [[0, 0, -1], [0, 0, -1]])


def test_the_batch_protocol_is_a_backend_method():
    """`Backend.batch` is what the pose and view tasks call when batch_size() > 1: a backend that
    says it batches overrides it, and the base names the backend that forgot to."""
    import pytest

    from ga3ce_prep.stages import BACKENDS, backend_class
    from ga3ce_prep.stages.base import Backend, BackendContext

    batching = [k for k in BACKENDS if backend_class(*k.split("/")).batch is not Backend.batch]
    assert batching == ["view/gfie"]

    class Forgetful(Backend):
        stage, name = "view", "forgetful"

        def batch_size(self) -> int:
            return 4

    with pytest.raises(NotImplementedError, match="Forgetful: batch_size"):
        Forgetful({}, BackendContext(Path("."))).batch([])
