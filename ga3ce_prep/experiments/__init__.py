"""Experiments as typed objects (docs/experiments.md): a `World` (a synthetic world and its store),
`Arm`s (ablation rows or designs, with recipe changes), an `Experiment` (worlds x arms x seeds, a
split, transfer worlds), run by `run_experiment` into one results file that carries its conditions
(conditions.py: the machine and the code). The named ones are in named.py."""
from .conditions import code, machine
from .experiment import Arm, Experiment, ensure_scored, format_results, mae_table, run_experiment
from .named import EXPERIMENTS, demo_experiment
from .world import World

__all__ = ["Arm", "EXPERIMENTS", "Experiment", "World", "code", "demo_experiment", "ensure_scored", "format_results",
           "machine", "mae_table", "run_experiment"]
