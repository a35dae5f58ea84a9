"""The view stage: the view prior v, a unit camera-frame vector (an appearance network's gaze
estimate). A failure drops the frame: GA3CE has nothing to refine without v.

Backends: `precomputed` (stages/precomputed.py layout) and `oracle` (the synthetic truth gaze,
optionally pulled toward the head direction, plus noise calibrated to a mean angular error:
stages/oracle_noise.py `noisy_view`; the paper's robustness protocol uses 20, 30 and 40 degrees).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import FrameError
from ..frames import FrameRef
from ..geometry import normalize
from ..params import param
from .base import ViewBackend
from .oracle_noise import frame_rng, noisy_view
from .precomputed import precomputed_table
from .truth import TruthParams, check_truth_file, truth_frame


class PrecomputedView(ViewBackend):
    """v from `file` (HDF5/npz: frame_id (N,), view (N, 3)); re-normalised."""

    name = "precomputed"

    @dataclass(frozen=True, kw_only=True)
    class Params:
        file: Path = param(file="data", hint="write it with the layout in docs/pipeline.md (frame_id, view)")  # HDF5/npz: frame_id (N,) str, view (N, 3)

    def _table(self):
        return precomputed_table(self.p.file, "view", (3,), "stages.view.params.file")

    def check(self) -> None:
        self._table()

    def view(self, frame: FrameRef) -> np.ndarray:
        v = self._table().get(frame.id)
        n = float(np.linalg.norm(v))
        if not np.isfinite(n) or n < 1e-6:
            raise FrameError(f"view of frame {frame.id} in {self.p.file} is {v.tolist()}, not a direction")
        return (v / n).astype(np.float32)


class OracleView(ViewBackend):
    """Truth gaze, pulled toward the head direction by head_weight, plus noise with mean angular
    error mean_error_deg against the truth gaze; seeded by (seed, frame id)."""

    name = "oracle"

    @dataclass(frozen=True, kw_only=True)
    class Params(TruthParams):
        seed: int = 0  # noise seed (combined with the frame id)
        mean_error_deg: float = param(20.0, minimum=0, maximum=90)  # mean angle between v and the truth gaze, degrees
        head_weight: float = param(0.0, minimum=0, maximum=1)  # pull of v toward the truth head direction before the noise (0: none, 1: centred on it)

    def check(self) -> None:
        check_truth_file(self.p.truth)

    def view(self, frame: FrameRef) -> np.ndarray:
        p = self.p
        rec = truth_frame(p.truth, frame.id, maps=False)
        gaze = np.asarray(rec.gaze, np.float64)
        if not np.all(np.isfinite(gaze)) or np.linalg.norm(gaze) < 1e-9:
            raise FrameError(f"truth gaze of frame {frame.id} is not a direction")
        head = getattr(rec, "head_dir", None)
        return noisy_view(normalize(gaze), None if head is None else np.asarray(head, np.float64),
                          frame_rng(p.seed, "view/oracle", frame.id), p.mean_error_deg, p.head_weight)
