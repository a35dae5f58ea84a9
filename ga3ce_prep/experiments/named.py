"""The named experiments: `ga3ce-prep experiment run NAME`. Each is a declaration; what runs them is
experiment.py. A figure in the docs names the experiment and the results file it came from."""
from __future__ import annotations

from .experiment import Arm, Experiment
from .world import World

# the rows of the paper's Tables 4 and 5 (train/ablate.py), then ours
PAPER_ROWS = ("appearance", "no-objects", "no-pose", "no-ga3ce", "full", "no-egocentric", "no-cyclotorsion", "no-d3")


def demo_experiment(rooms: int = 48, sessions: int = 4, frames: int = 15, transfer_rooms: int = 8, epochs: int = 20,
                    seed: int = 0) -> Experiment:
    """`make demo`'s experiment: the paper's GA3CE, ours and the model without objects on a seen-rooms
    GFIE-format world (test sessions of rooms seen in training), and on a transfer world of unseen
    rooms with another camera (CAD-120 format; none when transfer_rooms is 0)."""
    transfer = {"transfer": World(fmt="cad120", preset="transfer", rooms=transfer_rooms, sessions=1, frames=30,
                                  seed=seed)} if transfer_rooms else {}
    return Experiment(
        name="demo",
        question="Does the paper's GA3CE beat its no-objects ablation on rooms seen in training, and ours?",
        worlds={"synthetic": World(rooms=rooms, sessions=sessions, frames=frames, seed=seed)},
        arms=(Arm("full"), Arm("no-objects"), Arm("ours")),   # ours' g0 is the no-objects run
        seeds=(seed,), transfer=transfer, recipe={"epochs": epochs})


EXPERIMENTS: dict[str, Experiment] = {
    "demo": demo_experiment(),
    "paper-tables": Experiment(
        name="paper-tables",
        question="Do the paper's Tables 4 and 5 (input components, GA3CE's components) and its Table 2 "
                 "(transfer) hold on a seen-rooms world of 6,000 frames?",
        worlds={"large": World(rooms=60, sessions=5, frames=20, seed=8002)},
        arms=(*(Arm(r) for r in PAPER_ROWS), Arm("ours")),
        seeds=(0, 1, 2),
        transfer={"transfer": World(fmt="cad120", preset="transfer", rooms=16, sessions=1, frames=40, seed=8102)}),
}
