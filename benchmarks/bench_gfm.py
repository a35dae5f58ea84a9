"""What `eval --gfm` costs per frame on a CPU (docs/training.md, "GFIE's gaze-following modules"):
GFIE's network as `train/gfm.py::_score` runs it, per batch of B frames the head network once on B
head crops and the heatmap network once on 2 B (GFIE's g and ours), and the per-frame inputs
`_gfm_frame` makes (scene and head inputs, head channel, T from a full-resolution depth map).

The network is `estimators/view/gfie_net.py::GFIENet` with random weights (seed 0): the same layers
and sizes as GFIE's checkpoint, so the same arithmetic. The frame is a random 1920 x 1080 image
and depth map (GFIE's resolution). Each time is the best of `--repeat`, `--threads` torch threads,
as wall seconds and as this process's CPU seconds (with one thread on a busy machine, the CPU
seconds are what an idle core takes).

    python benchmarks/bench_gfm.py [--batch 16] [--threads 1] [--repeat 2]
"""
from __future__ import annotations

import time
from collections.abc import Callable

import click
import numpy as np


def _best(fn: Callable[[], object], repeat: int) -> tuple[float, float]:
    """The best wall and the best CPU seconds (this process) of `repeat` calls: on a busy machine
    the CPU seconds of a one-thread run are what an idle core would take."""
    wall, cpu = [], []
    for _ in range(repeat):
        t, c = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return min(wall), min(cpu)


@click.command()
@click.option("--batch", default=16, show_default=True, help="Frames per pass (eval's --gfm-batch-size).")
@click.option("--threads", default=1, show_default=True, help="torch CPU threads.")
@click.option("--repeat", default=2, show_default=True, help="Best of this many.")
def main(batch: int, threads: int, repeat: int) -> None:
    import torch

    from ga3ce_prep.estimators.view.gfie_net import RECIPES, GFIENet, head_location, matrix_t, scene_input
    from ga3ce_prep.estimators.view.head_crop import head_input

    torch.set_num_threads(threads)
    torch.manual_seed(0)
    net = GFIENet().eval()
    rng = np.random.default_rng(0)
    W, H = 1920, 1080
    rgb = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    depth = rng.uniform(0.5, 8.0, (H, W)).astype(np.float32)
    K = np.array([[1000.0, 0, W / 2], [0, 1000.0, H / 2], [0, 0, 1]])
    box, eye = np.array([900.0, 300.0, 1000.0, 420.0]), np.array([0.0, -0.2, 2.5])

    def inputs() -> dict[str, np.ndarray]:
        return {"scene": scene_input(rgb), "head": head_input(rgb, box), "head_loc": head_location(box, (W, H)),
                "matrix_t": matrix_t(depth, (W, H), K, eye, RECIPES["gfie"])}

    t_inputs = _best(inputs, max(repeat, 3))
    one = inputs()
    x = {k: torch.from_numpy(np.concatenate([v] * batch)) for k, v in one.items()}
    g = torch.nn.functional.normalize(torch.randn(batch, 3), dim=-1)
    with torch.inference_mode():
        t_head = _best(lambda: net.egd_module(x["head"]), repeat)
        t_heat = _best(lambda: net.heatmap(*(torch.cat([x[k], x[k]]) for k in ("scene", "head_loc", "matrix_t")),
                                           torch.cat([g, g])), repeat)
    print(f"batch {batch}, {threads} torch thread(s), best of {repeat}; seconds a frame, wall / CPU:")
    rows = [(f"head network ({batch} crops a pass)", t_head, batch),
            (f"heatmap network ({2 * batch} inputs a pass)", t_heat, batch),
            ("networks", (t_head[0] + t_heat[0], t_head[1] + t_heat[1]), batch),
            ("inputs (1920x1080: scene, head, T)", t_inputs, 1)]
    for name, (wall, cpu), n in rows:
        print(f"  {name:<36} {wall / n:6.3f} / {cpu / n:6.3f}")
    print(f"  heatmap passes: {t_heat[1] / (t_head[1] + t_heat[1]):.0%} of the networks' CPU seconds")


if __name__ == "__main__":
    main()
