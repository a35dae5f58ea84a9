"""The paper's qualitative figures for a trained run (matplotlib, Agg; PNG files).

- qualitative grid: frames from the best to the worst error, each drawn by `viz.draw_png` (the
  frame's 3D context on its image) with the ground-truth gaze (red), ours g (orange) and the view
  prior v (blue) as arrows projected from the head into the image;
- attention: the weight the model gives each object (`GA3CE.object_weights`: the pointer's p, or
  the paper's decoder's last-layer cross-attention, mean over heads), projected into the image, the
  objects above the frame's 95th percentile ringed in red, the gaze target (star) and the true gaze
  (red arrow) marked;
- egocentric space: the 3D context after `egocentric_transform` (v' = z): the objects P'_obj in
  metres (coloured by attention) and the pose P'_pose in head widths, with v', R g_gt and R g.

`make_figures(model, ds, out)` predicts the split, chooses the frames and writes all three.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..errors import Ga3ceError
from ..geometry import angular_error_deg, normalize, project
from ..model import GA3CE
from ..model.egocentric import egocentric_transform
from ..store import ContextStore
from ..viz import draw_png, find_frame_refs, frame_canvas
from .dataset import ContextDataset
from .evaluate import predict
from .plots import _pyplot

HIGHLIGHT_PERCENTILE = 95.0
ARROW_M = 0.6  # length of the arrows drawn from the head, metres (viz.draw_png's default)


@dataclass
class FigureFrames:
    """The frames the figures show (n of them, best to worst error) with the model's inputs and
    outputs. rows: (n,) store rows; pos: (n,) dataset positions; pred: (n, 3) g; error, prior_error:
    (n,) degrees of g and of v; objects: (n, S, 3) metres; mask: (n, S) True = real object;
    attention: (n, S) weight of each object (GA3CE.object_weights), None for a model without
    attention; null: (n,) the null token's weight (g0's, for the pointer; None likewise)."""

    rows: np.ndarray
    pos: np.ndarray
    pred: np.ndarray
    error: np.ndarray
    prior_error: np.ndarray
    objects: np.ndarray
    mask: np.ndarray
    attention: np.ndarray | None
    null: np.ndarray | None
    pointer: bool = False  # the weights are the pointer output's p (else the decoder's attention)


def choose_frames(errors: np.ndarray, n: int) -> np.ndarray:
    """Positions of n frames at evenly spaced quantiles (5%..95%) of `errors`, best first."""
    order = np.argsort(errors, kind="stable")
    q = np.linspace(0.05, 0.95, min(n, len(order))) if n > 1 else np.array([0.5])
    return order[np.unique(np.round(q * (len(order) - 1)).astype(np.int64))]


@torch.no_grad()
def figure_frames(model: GA3CE, ds: ContextDataset, n: int = 8, n_max: int | None = None,
                  device: str | torch.device = "cpu") -> FigureFrames:
    """Predict every frame of ds, choose n (choose_frames) and record the weight of each object."""
    g = predict(model, ds, device=device, n_max=n_max)
    err = angular_error_deg(g, ds.gaze)
    pos = choose_frames(err, n)
    b = ds.batch(pos, n_max)
    attention = null = None
    if model.config.use_context:
        model.eval()
        _, weights = model.object_weights(*(t.to(device) for t in (b.view, b.pose, b.head_pos, b.objects, b.mask)))
        w = weights.cpu().numpy()                                            # (n, 1 + S'), S' = 0 without objects
        null = w[:, 0]
        attention = np.zeros(b.mask.shape, np.float32)
        attention[:, : w.shape[1] - 1] = w[:, 1:]
    return FigureFrames(rows=ds.rows[pos], pos=pos, pred=g[pos], error=err[pos],
                        prior_error=angular_error_deg(ds.view[pos], ds.gaze[pos]),
                        objects=b.objects.numpy(), mask=b.mask.numpy(), attention=attention, null=null,
                        pointer=model.config.output == "pointer" and model.config.use_objects)


def _panels(n: int, cols: int, size: tuple[float, float], projection: str | None = None):
    plt = _pyplot()
    rows = -(-n // cols)
    fig = plt.figure(figsize=(size[0] * cols, size[1] * rows), dpi=100)
    axes = [fig.add_subplot(rows, cols, k + 1, projection=projection) for k in range(n)]
    return plt, fig, axes


def _save(plt, fig, path: str | Path) -> Path:
    fig.tight_layout(rect=(0, 0, 1, 0.95))                              # room for the title and a legend
    fig.savefig(path)
    plt.close(fig)
    return Path(path)


def plot_qualitative_grid(store: ContextStore, fr: FigureFrames, path: str | Path,
                          refs: dict | None = None, cols: int = 4) -> Path:
    """The qualitative grid (module docstring); refs: frame id -> FrameRef for the images."""
    refs = refs or {}
    plt, fig, axes = _panels(len(fr.rows), min(cols, len(fr.rows)), (4.2, 3.9))
    ids = store.frames["id"]
    for ax, i, g, e, ev in zip(axes, fr.rows, fr.pred, fr.error, fr.prior_error):
        img = draw_png(store, int(i), refs.get(ids[i]), arrow_m=ARROW_M, gaze_label="ground truth", pred=g)
        ax.imshow(img[..., ::-1])
        ax.set_title(f"ours {e:.1f}°, v {ev:.1f}°", fontsize=9)
        ax.axis("off")
    fig.suptitle("ground truth (red), ours g (orange), view prior v (blue); best to worst", fontsize=10)
    return _save(plt, fig, path)


def plot_attention(store: ContextStore, fr: FigureFrames, path: str | Path, refs: dict | None = None,
                   cols: int = 4) -> Path:
    """The model's weight of each object in the image (module docstring)."""
    if fr.attention is None or fr.null is None:  # both set, or neither (figure_frames)
        raise ValueError("these frames have no attention (a model without context, the appearance-only row)")
    refs = refs or {}
    plt, fig, axes = _panels(len(fr.rows), min(cols, len(fr.rows)), (4.2, 3.9))
    f, ids = store.frames, store.frames["id"]
    masked = np.where(fr.mask, fr.attention, np.nan)
    with np.errstate(all="ignore"):
        thr = np.nanpercentile(np.where(fr.mask.any(1, keepdims=True), masked, 0.0), HIGHLIGHT_PERCENTILE, axis=1)
    for k, (ax, i) in enumerate(zip(axes, fr.rows)):
        img, s = frame_canvas(store, int(i), refs.get(ids[i]))
        K = f["K"][i].astype(np.float64)
        ax.imshow(img[..., ::-1])
        real = fr.mask[k]
        uv, w = project(fr.objects[k][real], K) * s, fr.attention[k][real]
        ok = np.isfinite(uv).all(1)
        sc = ax.scatter(uv[ok, 0], uv[ok, 1], c=w[ok], s=15 + 400 * w[ok] / max(w.max(initial=0), 1e-9),
                        cmap="viridis", vmin=0, vmax=max(w.max(initial=0), 1e-9), edgecolors="k", linewidths=0.4)
        top = ok & (w > thr[k])
        ax.scatter(uv[top, 0], uv[top, 1], s=260, facecolors="none", edgecolors="red", linewidths=1.6,
                   label=f"> {HIGHLIGHT_PERCENTILE:g}th percentile")
        head = f["head_pos"][i].astype(np.float64)
        hg = project(np.stack([head, head + ARROW_M * normalize(f["gaze"][i].astype(np.float64))]), K) * s
        if np.isfinite(hg).all():
            ax.annotate("", hg[1], hg[0], arrowprops=dict(arrowstyle="->", color="red", lw=2))
            ax.plot(*hg[0], "+", color="yellow", ms=12, mew=2)
        t = project(f["gaze_target"][i].astype(np.float64), K) * s
        if np.isfinite(t).all():
            ax.plot(*t, "*", color="red", ms=16, mec="white", label="gaze target")
        fig.colorbar(sc, ax=ax, fraction=0.04, pad=0.01)
        ax.set_title(f"{ids[i]}\n{int(real.sum())} objects, {'g0' if fr.pointer else 'null token'} {fr.null[k]:.2f}",
                     fontsize=8)
        ax.set_xlim(0, img.shape[1])
        ax.set_ylim(img.shape[0], 0)
        ax.axis("off")
    fig.legend(*axes[0].get_legend_handles_labels(), loc="upper right", ncol=2, fontsize=8)
    fig.suptitle("the model's weight of each object (" + ("pointer p" if fr.pointer else
                 "decoder cross-attention, last layer, mean over heads") + ")", fontsize=10)
    return _save(plt, fig, path)


def plot_egocentric(fr: FigureFrames, ds: ContextDataset, model: GA3CE, path: str | Path, n: int = 3) -> Path:
    """The egocentric space of n of the frames, spread from best to worst (module docstring): the
    model's own transform (its rotation setting) of their 3D context; plotted with forward (z')
    into the page and up = -y'."""
    c = model.config
    k = np.unique(np.linspace(0, len(fr.rows) - 1, min(n, len(fr.rows))).round().astype(np.int64))
    b = ds.batch(fr.pos[k])
    ctx = egocentric_transform(b.view, b.pose, torch.from_numpy(fr.objects[k]), b.head_pos, c.rotation,
                               c.head_width_pair)
    R = ctx.R.numpy()
    gt, ours = np.einsum("bij,bj->bi", R, ds.gaze[fr.pos[k]]), np.einsum("bij,bj->bi", R, fr.pred[k])
    v_ego, objs, pose, valid = ctx.view.numpy(), ctx.objects.numpy(), ctx.pose.numpy(), ctx.joint_valid.numpy()
    m = len(R)
    plt, fig, axes = _panels(2 * m, m, (4.0, 3.8), projection="3d")

    def xyz(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # (x', z', -y'): up is up
        return p[..., 0], p[..., 2], -p[..., 1]

    mask, attention = fr.mask[k], None if fr.attention is None else fr.attention[k]
    for j in range(m):
        for ax, pts, ok, unit, length in ((axes[j], objs[j], mask[j], "m", 1.0),
                                          (axes[m + j], pose[j], valid[j], "head widths", 3.0)):
            w = attention[j][ok] if attention is not None and unit == "m" else None
            style = {"c": w, "cmap": "viridis"} if w is not None else {"color": "grey" if unit == "m" else "m"}
            ax.scatter(*xyz(pts[ok]), s=14, **style)
            ax.scatter(0, 0, 0, color="gold", s=40, marker="x")
            for vec, colour, label in ((v_ego[j], "blue", "v' (= z')"), (gt[j], "red", "R g_gt"),
                                       (ours[j], "orange", "R g")):
                ax.quiver(0, 0, 0, *(length * np.array(xyz(vec))), color=colour, label=label, arrow_length_ratio=0.15)
            ax.set_xlabel(f"x' ({unit})", fontsize=7)
            ax.set_ylabel(f"z' ({unit})", fontsize=7)
            ax.set_zlabel(f"-y' ({unit})", fontsize=7)
            ax.tick_params(labelsize=6)
            ax.set_aspect("equal")
            ax.locator_params(nbins=4)
        axes[j].set_title(f"{ds.store.frames['id'][fr.rows[k][j]]}\nobjects P'_obj", fontsize=8)
        axes[m + j].set_title("pose P'_pose", fontsize=8)
    axes[0].legend(loc="upper left", fontsize=6)
    fig.suptitle(f"egocentric space (rotation: {c.rotation})", fontsize=10)
    return _save(plt, fig, path)


def make_figures(model: GA3CE, ds: ContextDataset, out: str | Path, n: int = 8, n_max: int | None = None,
                 data: str | Path | None = None, device: str | torch.device = "cpu") -> dict[str, Path]:
    """Write qualitative.png, attention.png (models with context) and egocentric.png into out for
    n frames of ds; data: the dataset folder for the images (default: the one the store records).
    Returns {name: path}."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    fr = figure_frames(model, ds, n, n_max, device)
    try:  # the images are optional: without the dataset the panels are drawn on grey
        refs = find_frame_refs(ds.store, ds.store.frames["id"][fr.rows].tolist(), data)
    except (Ga3ceError, KeyError, OSError, TypeError):
        refs = {}
    paths = {"qualitative": plot_qualitative_grid(ds.store, fr, out / "qualitative.png", refs)}
    if fr.attention is not None:
        paths["attention"] = plot_attention(ds.store, fr, out / "attention.png", refs)
    paths["egocentric"] = plot_egocentric(fr, ds, model, out / "egocentric.png")
    return paths
