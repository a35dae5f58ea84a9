"""The view stage: the view prior v, a unit camera-frame vector (an appearance network's gaze
estimate). A failure drops the frame: GA3CE has nothing to refine without v.

Backends: `precomputed` (stages/precomputed.py layout) and `oracle` (the synthetic truth gaze,
optionally pulled toward the head direction, plus noise calibrated to a mean angular error:
stages/noise.py `noisy_view`; the paper's robustness protocol uses 20, 30 and 40 degrees).
"""
from __future__ import annotations

import numpy as np

from ..errors import FrameError
from ..frames import FrameRef
from ..geometry import normalize
from .base import ViewBackend
from .noise import frame_rng, noisy_view
from .precomputed import precomputed_table
from .truth import truth_record


class PrecomputedView(ViewBackend):
    """v from `file` (HDF5/npz: frame_id (N,), view (N, 3)); re-normalised."""

    name = "precomputed"

    def check(self) -> None:
        precomputed_table(self.params["file"], "view", (3,), "stages.view.params.file")

    def view(self, frame: FrameRef) -> np.ndarray:
        v = precomputed_table(self.params["file"], "view", (3,), "stages.view.params.file").get(frame.id)
        n = float(np.linalg.norm(v))
        if not np.isfinite(n) or n < 1e-6:
            raise FrameError(f"view of frame {frame.id} in {self.params['file']} is {v.tolist()}, not a direction")
        return (v / n).astype(np.float32)


class OracleView(ViewBackend):
    """Truth gaze, pulled toward the head direction by head_weight, plus noise with mean angular
    error mean_error_deg against the truth gaze; seeded by (seed, frame id)."""

    name = "oracle"

    def check(self) -> None:
        truth_record.check(self.params["truth"])

    def view(self, frame: FrameRef) -> np.ndarray:
        p = self.params
        rec = truth_record(p["truth"], frame.id, maps=False)
        gaze = np.asarray(rec.gaze, np.float64)
        if not np.all(np.isfinite(gaze)) or np.linalg.norm(gaze) < 1e-9:
            raise FrameError(f"truth gaze of frame {frame.id} is not a direction")
        head = getattr(rec, "head_dir", None)
        return noisy_view(normalize(gaze), None if head is None else np.asarray(head, np.float64),
                          frame_rng(p["seed"], "view/oracle", frame.id), p["mean_error_deg"], p["head_weight"])
