"""A Rerun recording (.rrd) read back with Rerun's own reader (rerun.chunk.RrdReader), for the tests
and the view benchmark: every logged row by entity, with its timelines and components."""
from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any


@dataclass
class Recording:
    """rows[entity]: one dict per logged row, {timeline: int, component ("Points3D:positions"): its
    Python value}, in time order of `row` (static rows first); nbytes[entity]: the entity's bytes
    as Arrow holds them once read (uncompressed)."""

    rows: dict[str, list[dict[str, Any]]] = field(default_factory=dict)
    nbytes: dict[str, int] = field(default_factory=dict)

    def at(self, entity: str, timeline: str) -> dict[int, dict[str, Any]]:
        """The entity's rows on `timeline`, by their time on it (a time logged twice: the last)."""
        return {r[timeline]: r for r in self.rows.get(entity, []) if timeline in r}

    def static(self, entity: str) -> list[dict[str, Any]]:
        return [r for r in self.rows.get(entity, []) if r["static"]]

    def timelines(self) -> set[str]:
        return {k for rows in self.rows.values() for r in rows for k, v in r.items()
                if isinstance(v, int) and not isinstance(v, bool) and ":" not in k}


def read_recording(path: str | Path, blobs: bool = True) -> Recording:
    """Every chunk of the recording at `path` (its first recording store), as `Recording`. blobs=False
    leaves out image and blob bytes (Image:buffer, *:blob, SegmentationImage:buffer)."""
    from rerun.chunk import RrdReader

    rows: dict[str, list[dict[str, Any]]] = defaultdict(list)
    nbytes: dict[str, int] = defaultdict(int)
    for chunk in RrdReader(str(path)).stream():
        rb = chunk.to_record_batch()
        entity = chunk.entity_path
        nbytes[entity] += rb.nbytes
        names = [n for n in rb.schema.names if not n.startswith("rerun.controls") and n != "log_time"
                 and (blobs or not n.endswith((":buffer", ":blob", ":contents")))]
        columns = {n: rb.column(n).to_pylist() for n in names}
        for k in range(rb.num_rows):
            row = {n: columns[n][k] for n in names if columns[n][k] is not None}
            row["static"] = chunk.is_static
            rows[entity].append(row)
    for entity in rows:
        rows[entity].sort(key=lambda r: (not r["static"], r.get("row", -1)))
    return Recording(dict(rows), dict(nbytes))
