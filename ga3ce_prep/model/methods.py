"""The trainable designs by fixed name, the way `ga3ce-prep train --model NAME` chooses them.

A design's name never changes meaning (as nerfstudio's `nerfacto` names one design): a new design
gets a new name. `ours` is an alias, not a design: it names the design we currently think best,
and is resolved to that fixed name wherever a model is made (`ModelConfig.for_method`), so the
checkpoint's config, the eval table and `ablate`'s output name the design, not the alias.

- `ga3ce`: the paper's GA3CE, the default everywhere. Its 3D gaze transformer reads the subject
  token against the objects (encoder over [null token, objects], decoder over the subject token,
  the gaze-cone bias in cross-attention) and regresses g' (ModelConfig.output "regress").
- `pointer-joint`: GA3CE's egocentric transform and encodings with a pointer output: a first pass
  without objects gives g0, trained jointly with the pointer (pointer_g0 "joint"), then g is g0 or
  an object's direction near it (output "pointer"; docs/training.md, "The output"). `ours` from
  commit 6147290 (2026-11-29, then the default output) to 59f75a3 (2026-12-01).
- `pointer-frozen`: the same pointer, but g0 is the model without objects, trained first and
  frozen (pointer_g0 "frozen"); chosen over pointer-joint on the validation splits of three
  worlds (the objects-value driver's choosing phase, 01a7406:benchmarks/objects_value.py). `ours`
  since commit 59f75a3 (2026-12-01).

Before 6147290 the only model was the paper's (every study of then measured `ga3ce`).
`ALIAS_HISTORY` records which design `ours` named when, so a checkpoint that stored the alias
(written before the fixed names) loads as the design it was (`saved_design`).

A design is a set of ModelConfig values (`ModelConfig.for_method(name)` builds it); an ablation
(train/ablate.py) switches parts of it off. `model_label` (model/ga3ce.py, beside ModelConfig) names
any config for the printed tables; this module imports nothing of the model's.
"""
from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

log = logging.getLogger("ga3ce_prep.model")


@dataclass(frozen=True)
class Method:
    """A design by its fixed name: its ModelConfig values and how tables name it."""

    name: str                 # `--model NAME`; never changes meaning
    label: str                # its row in every printed table
    summary: str              # one line: what it is
    config: dict[str, Any] = field(default_factory=dict)   # ModelConfig fields it sets


METHODS: dict[str, Method] = {m.name: m for m in (
    Method("ga3ce", "GA3CE (paper)",
           "the paper's model: a 3D gaze transformer over the objects regresses the gaze",
           {"output": "regress"}),
    Method("pointer-joint", "pointer-joint",
           "a first pass without objects gives g0 (trained jointly with the pointer); a pointer then picks g0 "
           "or an object near it",
           {"output": "pointer", "pointer_g0": "joint"}),
    Method("pointer-frozen", "pointer-frozen",
           "the model without objects gives g0 (trained first, then frozen); a pointer then picks g0 or an "
           "object near it",
           {"output": "pointer", "pointer_g0": "frozen"}),
)}
DEFAULT_METHOD = "ga3ce"
# alias -> the fixed design it names today
ALIASES: dict[str, str] = {"ours": "pointer-frozen"}
# alias -> (design, commit from which the alias named it, that commit's date), oldest first
ALIAS_HISTORY: dict[str, tuple[tuple[str, str, str], ...]] = {
    "ours": (("pointer-joint", "6147290", "2026-11-29"), ("pointer-frozen", "59f75a3", "2026-12-01")),
}
NO_OBJECTS_LABEL = "no objects (app. + pose)"


def resolve(name: str) -> str:
    """The fixed design `name` stands for: an alias's design today, a design's own name; ValueError
    naming the choices otherwise."""
    design = ALIASES.get(name, name)
    if design not in METHODS:
        raise ValueError(f"unknown model {name!r}; choose one of {', '.join([*METHODS, *ALIASES])}")
    return design


def aliases_of(design: str) -> list[str]:
    """The aliases that name `design` today ("ours" for the current best)."""
    return [a for a, d in ALIASES.items() if d == design]


def saved_design(name: str, saved: Mapping[str, Any]) -> str:
    """The fixed design a saved model config (`saved`: its fields, defaults filled in) that
    recorded `name` was: `name` itself when it is a design; for an alias (checkpoints written before
    the fixed names stored "ours"), the design the alias has named whose values the config holds.
    When none or several of those match, the alias's design today, with a warning."""
    if name in METHODS:
        return name
    if name not in ALIASES:
        raise ValueError(f"unknown model {name!r}; choose one of {', '.join([*METHODS, *ALIASES])}")
    named = [d for d, _, _ in ALIAS_HISTORY.get(name, ())]
    match = [d for d in named if all(saved.get(k) == v for k, v in METHODS[d].config.items())]
    if len(match) == 1:
        return match[0]
    log.warning("a saved model config names %r, which matches %s of the designs %r has named (%s); reading it as "
                "%r, the design %r names today", name, "none" if not match else "several", name, ", ".join(named),
                ALIASES[name], name)
    return ALIASES[name]
