"""The trainable methods by name, the way `ga3ce-prep train --model NAME` chooses them.

- `ga3ce`: the paper's GA3CE, the default everywhere. Its 3D gaze transformer reads the subject
  token against the objects (encoder over [null token, objects], decoder over the subject token,
  the gaze-cone bias in cross-attention) and regresses g' (ModelConfig.output "regress").
- `ours`: our design, whatever it is at the time (its full config is saved in each checkpoint).
  Today: GA3CE's egocentric transform and encodings with a pointer output: g0 is the model
  without objects, trained first and frozen (pointer_g0 "frozen"), then g is g0 or an object's
  direction near it (output "pointer"; chosen over training g0 jointly on the validation splits
  of three worlds: benchmarks/objects_value.py --phase choose;
  docs/training.md, "The output").

A method is a set of ModelConfig values (`ModelConfig.for_method(name)` builds it); an ablation
(train/ablate.py) switches parts of it off. `model_label` (model/ga3ce.py, beside ModelConfig) names
any config for the printed tables; this module imports nothing of the model's.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True)
class Method:
    """A named model: its ModelConfig values and how tables name it."""

    name: str                 # `--model NAME`
    label: str                # its row in every printed table
    summary: str              # one line: what it is
    config: dict[str, Any] = field(default_factory=dict)   # ModelConfig fields it sets


METHODS: dict[str, Method] = {m.name: m for m in (
    Method("ga3ce", "GA3CE (paper)",
           "the paper's model: a 3D gaze transformer over the objects regresses the gaze",
           {"output": "regress"}),
    Method("ours", "ours",
           "the model without objects gives g0 (trained first, then frozen); a pointer then picks g0 or an "
           "object near it",
           {"output": "pointer", "pointer_g0": "frozen"}),
)}
DEFAULT_METHOD = "ga3ce"
NO_OBJECTS_LABEL = "no objects (app. + pose)"
