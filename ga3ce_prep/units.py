"""Lengths in files: their conversion to metres, and the physical ranges that catch a file in the
wrong unit (an 8-bit depth PNG read as millimetres, a pose in millimetres stored as metres,
centimetres taken for millimetres) before it is stored.

The checks look at a median (robust to holes and outliers), compare it with what a depth sensor,
a room or a person can measure, and refuse what cannot be right, naming the source, the value
found, the units that would fit and the setting that fixes it. Every adapter and backend that
reads lengths checks them here (docs/datasets.md, "What is checked").
"""
from __future__ import annotations

from typing import Literal

import numpy as np
import numpy.typing as npt

from .errors import FrameError

Units = Literal["m", "cm", "mm", "inverse_m"]
LengthUnits = Literal["m", "cm", "mm"]
LENGTH_UNITS: tuple[str, ...] = ("m", "cm", "mm")
METRES_PER_UNIT: dict[str, float] = {"m": 1.0, "cm": 0.01, "mm": 0.001}

# Physical ranges, metres.
DISTANCE_RANGE_M: tuple[float, float] = (0.1, 100.0)  # a median distance from the camera: of one depth map (any
                                                      # sensor or estimator), of the people in a dataset
ROOM_RANGE_M: tuple[float, float] = (0.5, 10.0)       # the same over a room-scale dataset (GFIE, a Kinect
                                                      # recording), to infer a unit: m, cm and mm rarely both fit
BODY_RANGE_M: tuple[float, float] = (0.1, 3.0)        # one person's size: the largest distance between two joints


def lo_hi(plausible: tuple[float, ...]) -> str:
    """"0.5-10 m": a range as messages write it."""
    return f"{plausible[0]:g}-{plausible[1]:g} m"


def units_name(scale: float) -> str:
    """The unit a metres-per-stored-unit scale stands for ("mm" for 0.001), else "x<scale> m"."""
    return next((u for u, m in METRES_PER_UNIT.items() if np.isclose(scale, m)), f"x{scale:g} m")


def to_metres(x: npt.ArrayLike, units: str) -> np.ndarray:
    """A length array in `units` (m, cm, mm, inverse_m) as float32 metres; inverse values <= 0 give 0."""
    x = np.asarray(x, np.float32)
    if units == "inverse_m":
        with np.errstate(divide="ignore"):
            return np.where(x > 0, 1.0 / x, 0.0).astype(np.float32)
    return x if units == "m" else x * np.float32(METRES_PER_UNIT[units])


def fitting_units(raw: float | np.floating, plausible: tuple[float, ...],
                  candidates: tuple[str, ...] = LENGTH_UNITS) -> list[str]:
    """The units among `candidates` in which the value `raw` is within `plausible` [min, max] metres."""
    lo, hi = plausible
    return [u for u in candidates if lo <= float(to_metres(np.float32(raw), u)) <= hi]


def check_plausible(metres: np.ndarray, raw: np.ndarray, units: str, plausible: tuple[float, ...], what: str,
                    fix: str, quantity: str = "depth", error: type[Exception] = FrameError,
                    candidates: tuple[str, ...] = (*LENGTH_UNITS, "inverse_m")) -> None:
    """`error` unless the median of the positive values of `metres` lies in `plausible` [min, max]
    metres. `raw`: the same values in the source's `units`, to name which of `candidates` would
    fit; `what` names the source (file, frame), `quantity` what the values are, `fix` the setting
    to change."""
    pos = metres[metres > 0]
    if not pos.size:
        raise error(f"{what}: no positive {quantity} (all values are 0, negative or not finite)")
    med = float(np.median(pos))
    if plausible[0] <= med <= plausible[1]:
        return
    r = np.float32(np.median(np.asarray(raw)[metres > 0]))
    fits = [f"{u} ({float(to_metres(r, u)):.3g} m)" for u in fitting_units(r, plausible, candidates) if u != units]
    hint = f"; read as {' or '.join(fits)} it would be plausible" if fits else ""
    raise error(f"{what}: median {quantity} {med:.4g} m (read as units {units}) is outside the plausible "
                f"{lo_hi(plausible)}{hint}: set {fix}")


def infer_units(raw: np.ndarray, what: str, fix: str, error: type[Exception], quantity: str = "depth",
                plausible: tuple[float, ...] = ROOM_RANGE_M) -> str:
    """The one length unit (m, cm or mm) in which the median of the positive finite `raw` values is
    a plausible room-scale distance; `error` naming the median and the readings when no unit or
    more than one fits (then the user states the unit with `fix`)."""
    raw = np.asarray(raw, np.float64)
    pos = raw[np.isfinite(raw) & (raw > 0)]
    if not pos.size:
        raise error(f"{what}: no positive {quantity} to tell its units from; set {fix}")
    med = float(np.median(pos))
    fits = fitting_units(med, plausible)
    if len(fits) == 1:
        return fits[0]
    readings = ", ".join(f"{u} -> {med * METRES_PER_UNIT[u]:.3g} m" for u in LENGTH_UNITS)
    why = "fits none of m, cm, mm" if not fits else f"fits {' and '.join(fits)} alike"
    raise error(f"{what}: median {quantity} {med:.4g} {why} for a room-scale {lo_hi(plausible)} ({readings}); "
                f"set {fix}")


def pose_size(joints: np.ndarray) -> float:
    """A pose's size: the largest distance between two of its finite joints ((J, 3) in any length
    unit), NaN with fewer than two."""
    j = np.asarray(joints, np.float64)
    j = j[np.isfinite(j).all(1)]
    if len(j) < 2:
        return float("nan")
    return float(np.linalg.norm(j[:, None] - j[None], axis=-1).max())
