"""The named experiments: `ga3ce-prep experiment run NAME`. Each is a declaration; what runs them is
experiment.py. A figure in the docs names the experiment and the results file it came from.

World names are folder names under the output folder, so two experiments that name a world alike
share it (the demo's `synthetic`), and worlds that differ name themselves apart."""
from __future__ import annotations

from .experiment import Arm, Experiment
from .world import World

SEEDS = (0, 1, 2)
# the rows of the paper's Tables 4 and 5 (train/ablate.py)
PAPER_ROWS = ("appearance", "no-objects", "no-pose", "no-ga3ce", "full", "no-egocentric", "no-cyclotorsion", "no-d3")
# the paper's GA3CE, its no-objects ablation and ours (whose g0 is the no-objects run: trained before it)
THREE = (Arm("full"), Arm("no-objects"), Arm("ours"))

DEMO_WORLD = World(rooms=48, sessions=4, frames=15, seed=0)
# Table 2's world for the report experiments: CAD-120 format, unseen rooms, another camera
TRANSFER_640 = World(fmt="cad120", preset="transfer", rooms=16, sessions=1, frames=40, seed=8102)

# Other rooms, camera mounts and intrinsics than the default world's (docs/synthetic.md).
OTHER_KNOBS = """\
room: {size_x: [3.5, 5.5], size_y: [3.5, 5.5], height: [2.4, 2.8]}
objects: {count: [20, 80]}
camera: {height: [2.0, 3.0], distance: [2.0, 5.0], pitch_offset: 12.0, fx: 610.0, fy: 610.0, cx: 312.0, cy: 246.0}
"""
# segmenter -> (pipeline, its settings, frames per shard: one camera session for `reuse: sequence`)
SEGMENTERS: dict[str, tuple[str, tuple[str, ...], bool]] = {
    "geometric": ("synthetic", (), False),
    "truth": ("synthetic-oracle", (), False),
    # 32x32 prompts: a 16x16 grid loses a third of the objects it finds within 10 cm (objects-quality study)
    "minisam": ("synthetic-minisam", ("stages.objects.params.reuse=sequence",), True),
    # prompted by depth (objects-quality study: ...)
    "minisam-depth": ("synthetic-minisam-depth", (), False),
}


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
        arms=THREE, seeds=(seed,), transfer=transfer, recipe={"epochs": epochs})


def objects_value(segmenter: str = "geometric") -> Experiment:
    """What the objects add on worlds no design was chosen on (seeds drawn after the choice), with
    the objects of `segmenter`: the paper's GA3CE, ours and no objects, three seeds, test split."""
    pipeline, settings, per_session = SEGMENTERS[segmenter]
    tag = "" if segmenter == "geometric" else f"-{segmenter}"

    def world(name: str, rooms: int, frames: int, seed: int, knobs: str | None = None,
              train_frames: int | None = None) -> World:   # one dataset for every segmenter's store
        return World(rooms=rooms, sessions=1, frames=frames, seed=seed, knobs=knobs, train_frames=train_frames,
                     pipeline=pipeline, overrides=settings, shard_size=frames if per_session else None, data=name)

    worlds = {"ov-small": world("ov-small", 28, 40, 7001), "ov-medium": world("ov-medium", 48, 60, 7002),
              "ov-other": world("ov-other", 40, 50, 7003, knobs=OTHER_KNOBS),
              "ov-large": world("ov-large", 750, 12, 7004, train_frames=6000)}
    return Experiment(
        name=f"objects-value{tag}",
        question=f"What do the objects ({segmenter}) add to the paper's GA3CE and to ours over no objects, on "
                 "unseen-room worlds of four sizes and knobs?",
        worlds={name + tag: w for name, w in worlds.items()}, arms=THREE, seeds=SEEDS)


def objects_value_seen(segmenters: tuple[str, ...] = ("geometric", "minisam-depth"), rooms: int = 48,
                       seed: int = 7101) -> Experiment:
    """What the objects of each segmenter add on one seen-rooms world (the demo's sizes, a seed drawn
    after the choice): the paper's GA3CE, ours and no objects, three seeds, test split; one store per
    segmenter of the same dataset."""
    def world(segmenter: str) -> World:
        pipeline, settings, per_session = SEGMENTERS[segmenter]
        return World(rooms=rooms, sessions=4, frames=15, seed=seed, pipeline=pipeline, overrides=settings,
                     shard_size=15 if per_session else None, data="ovs")

    return Experiment(
        name="objects-value-seen",
        question=f"What do the objects ({', '.join(segmenters)}) add to the paper's GA3CE and to ours over no "
                 "objects, on a seen-rooms world?",
        worlds={f"ovs-{s}": world(s) for s in segmenters}, arms=THREE, seeds=SEEDS)


EXPERIMENTS: dict[str, Experiment] = {e.name: e for e in (
    demo_experiment(),
    Experiment(
        name="demo-seeds",
        question="The demo's comparison over three seeds, and its Table 2 on a 640-frame transfer world",
        worlds={"synthetic": DEMO_WORLD}, arms=THREE, seeds=SEEDS, transfer={"transfer640": TRANSFER_640}),
    Experiment(
        name="paper-tables",
        question="Do the paper's Tables 4 and 5 (input components, GA3CE's components) and its Table 2 "
                 "(transfer) hold on a seen-rooms world of 6,000 frames?",
        worlds={"large": World(rooms=60, sessions=5, frames=20, seed=8002)},
        arms=(*(Arm(r) for r in PAPER_ROWS), Arm("ours")), seeds=SEEDS, transfer={"transfer640": TRANSFER_640}),
    *(objects_value(s) for s in SEGMENTERS),
    objects_value_seen(),
)}
