"""What an arm gains over another, with an interval over test sessions.

A results file (experiment.py `run_experiment`) holds, per run and scored split, each session's
frames and 3D MAE (`sessions`). The gain of arm A over arm B is 1 - MAE(A) / MAE(B), frames
weighted, each session's MAE averaged over the training seeds both arms have. Its interval
resamples the test sessions with replacement, within each world (the worlds are few: each keeps
its own sessions), A and B on the same draw (paired), and takes the 2.5 and 97.5 percentiles.
What it leaves out is said beside it: the spread over training seeds (`per_seed`) and over worlds
(`per_world`).
"""
from __future__ import annotations

from typing import Any

import numpy as np


def session_table(results: dict[str, Any], world: str, arm: str, scored_on: str | None = None
                  ) -> tuple[list[str], np.ndarray, dict[int, np.ndarray], np.ndarray]:
    """One arm on one scored world: the sessions (names), their frames (S,), per seed the
    sessions' 3D MAE (S,), and v's (S,)."""
    on = scored_on or world
    rows = [s for s in results["scores"] if s["world"] == world and s["arm"] == arm and s["scored_on"] == on]
    if not rows:
        raise KeyError(f"no scores of arm {arm!r} trained on {world!r} scored on {on!r}")
    names = sorted(rows[0]["sessions"])
    n = np.array([rows[0]["sessions"][k][0] for k in names], float)
    prior = np.array([rows[0]["sessions"][k][2] for k in names], float)
    return names, n, {r["seed"]: np.array([r["sessions"][k][1] for k in names], float) for r in rows}, prior


def gain(results: dict[str, Any], worlds: list[str], arm: str, base: str, scored_on: str | None = None,
         n_boot: int = 4000, seed: int = 0) -> dict[str, Any]:
    """The gain of `arm` over `base` (1 - MAE ratio; > 0: arm errs less) pooled over `worlds`, with
    its 95% session-bootstrap interval, per world and per seed; and both MAEs and v's."""
    rng = np.random.default_rng(seed)
    parts = []
    for w in worlds:
        names, n, a, prior = session_table(results, w, arm, scored_on)
        names_b, n_b, b, _ = session_table(results, w, base, scored_on)
        if names != names_b:
            raise ValueError(f"{w}: arms {arm} and {base} were scored on different sessions")
        seeds = sorted(set(a) & set(b))
        parts.append((n, np.mean([a[s] for s in seeds], 0), np.mean([b[s] for s in seeds], 0), prior,
                      {s: (a[s], b[s]) for s in seeds}))

    def ratio(idx: list[np.ndarray]) -> float:
        num = sum(float((n[i] * ma[i]).sum()) for (n, ma, _, _, _), i in zip(parts, idx))
        den = sum(float((n[i] * mb[i]).sum()) for (n, _, mb, _, _), i in zip(parts, idx))
        return num / den

    every = [np.arange(len(p[0])) for p in parts]
    boot = [1 - ratio([rng.integers(0, len(p[0]), len(p[0])) for p in parts]) for _ in range(n_boot)]
    frames = sum(float(p[0].sum()) for p in parts)

    def mae(k: int) -> float:
        return sum(float((p[0] * p[k]).sum()) for p in parts) / frames

    seeds = sorted(set.intersection(*(set(p[4]) for p in parts)))
    per_seed = {s: 1 - sum(float((p[0] * p[4][s][0]).sum()) for p in parts)
                / sum(float((p[0] * p[4][s][1]).sum()) for p in parts) for s in seeds}
    return {"arm": arm, "base": base, "gain": 1 - ratio(every),
            "low": float(np.percentile(boot, 2.5)), "high": float(np.percentile(boot, 97.5)),
            "mae": mae(1), "base_mae": mae(2), "v_prior": mae(3),
            "sessions": int(sum(len(p[0]) for p in parts)), "frames": int(frames), "seeds": seeds,
            "per_world": {w: float(1 - (p[0] * p[1]).sum() / (p[0] * p[2]).sum()) for w, p in zip(worlds, parts)},
            "per_seed": per_seed}


def format_gain(g: dict[str, Any]) -> str:
    """E.g. "full over no-objects: +4.1% [+1.2, +6.9] (15.02 vs 15.66; v 19.41; 33 sessions, 660 frames)"."""
    return (f"{g['arm']} over {g['base']}: {100 * g['gain']:+.1f}% [{100 * g['low']:+.1f}, {100 * g['high']:+.1f}] "
            f"({g['mae']:.2f} vs {g['base_mae']:.2f}; v {g['v_prior']:.2f}; {g['sessions']} sessions, "
            f"{g['frames']} frames; per seed " + " / ".join(f"{100 * v:+.1f}" for v in g["per_seed"].values())
            + "; per world " + " / ".join(f"{100 * v:+.1f}" for v in g["per_world"].values()) + ")")


def target_gains(results: dict[str, Any], worlds: list[str], arm: str, base: str) -> dict[str, tuple[float, int]]:
    """The gain of `arm` over `base` on the frames whose gaze target is at a stored object and on
    the others (ensure_scored's `target`), pooled over `worlds` and the seeds both have: {group:
    (gain, frames per seed)}; empty when the scores do not split by target or no target is at an
    object (a dataset without gaze target points, as GAFA's)."""
    out: dict[str, tuple[float, int]] = {}
    for group in ("at_object", "elsewhere"):
        num = den = 0.0
        frames = 0
        for w in worlds:
            rows = {(s["arm"], s["seed"]): s for s in results["scores"]
                    if s["world"] == w and s["scored_on"] == w and s["arm"] in (arm, base)}
            if not all("target" in s for s in rows.values()):
                return {}
            for seed in sorted({k for a, k in rows if a == arm} & {k for a, k in rows if a == base}):
                n, ma, _ = rows[(arm, seed)]["target"][group]
                _, mb, _ = rows[(base, seed)]["target"][group]
                if n:
                    num, den = num + n * ma, den + n * mb
            frames += next(iter(rows.values()))["target"][group][0]
        out[group] = (1 - num / den if den else float("nan"), frames)
    # no frame's target at an object: the annotation gives no target point (GAFA's: a direction)
    return out if out["at_object"][1] else {}
