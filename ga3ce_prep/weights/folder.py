"""The model folder (`{models}` in pipeline files: `--models`, else $GA3CE_MODEL_DIR, else ./models)
as a contract: every file the paper's pipelines read there, the command that writes it under that
name, about how large it is and how it is checked (`MODEL_FILES`, the table of
docs/models/README.md), and `ga3ce-prep models check`, which lists what a folder holds for a
pipeline: verified (the backend's own check passed), present (not checked: a file it is checked
with is missing), failing its check, or missing, with the command that makes each missing file
(ga3ce_prep/weights/cli.py loads the pipelines for it; pipeline/config.py finds each stage's files,
`stage_files`, and checks them, `check_stage`). `run` refuses a pipeline whose model files are
missing with the same lines (`missing_lines`)."""
from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

# the bundled pipelines of the paper's settings, all reading the one model folder
PAPER_PIPELINES: tuple[str, ...] = ("gfie", "cad120", "gafa", "gfie-monodepth")


@dataclass(frozen=True)
class ModelFile:
    """One file of the model folder: its name there, what it is, the command that writes it into the
    folder `models` (the recipe's own words), the recipe's page and section, about how large it is
    and what the backend's check verifies."""

    name: str
    what: str
    make: str
    page: str
    section: str
    size: str
    check: str

    @property
    def doc(self) -> str:
        """The recipe's page and section, as the docs cite them."""
        return f'docs/models/{self.page}, "{self.section}"'


_MOBILESAM = "ga3ce-prep export-mobilesam --checkpoint weights/mobile_sam.pt --out models"
_METRABS = "python scripts/export_crop_pose.py metrabs --model-dir metrabs_eff2l_384px_800k_28ds_pytorch --out models"
_CROP_CHECK = ("the joint list names all 30 smpl+head_30 joints; one grey crop of the model's side gives "
               "[1, J, 3], J the list's length")
MODEL_FILES: tuple[ModelFile, ...] = (
    ModelFile("mobile_sam_encoder.onnx", "MobileSAM's image encoder (TinyViT)", _MOBILESAM,
              "segment-everything.md", "Exporting from a trained `mobile_sam.pt`",
              "27.8 MB (the tests' random-weight export of the same graph)",
              "ONNX Runtime loads it: image [1, 3, 1024, 1024] in, embeddings [1, 256, 64, 64] out"),
    ModelFile("mobile_sam_decoder.onnx", "MobileSAM's prompt encoder and mask decoder", _MOBILESAM,
              "segment-everything.md", "Exporting from a trained `mobile_sam.pt`",
              "16.5 MB (the tests' random-weight export of the same graph)",
              "ONNX Runtime loads it: SAM's six prompt inputs; masks, iou_predictions, low_res_masks out"),
    ModelFile("metrabs.pt", "MeTRAbs's crop model, TorchScript (pose: torchscript)", _METRABS,
              "pose.md", "Making the files", "about 0.5 GB (EfficientNetV2-L, not measured here)",
              f"torch.jit.load; {_CROP_CHECK}"),
    ModelFile("metrabs.onnx", "MeTRAbs's crop model, ONNX (pose: onnx), where it exports", _METRABS,
              "pose.md", "Making the files", "about 0.5 GB (EfficientNetV2-L, not measured here)",
              f"ONNX Runtime loads it: image [N, S, S, 3], intrinsics [N, 3, 3]; {_CROP_CHECK}"),
    ModelFile("metrabs.joints.txt", "the crop model's joint names, one a line, beside it", _METRABS,
              "pose.md", "Making the files", "under 1 kB (30 names)", "read with the model above"),
    ModelFile("gfiemodel.pt.tar", "GFIE's released checkpoint (view: gfie)", "cp gfiemodel.pt.tar models/",
              "view.md", "GFIE's head network (`view: gfie`)",
              "207 MB or more (GFIE's network: 51.8 M parameters, as the tests' stand-in)",
              "torch.load (weights only): the head network's egd_module.* keys and shapes"),
    ModelFile("zoedepth.onnx", "ZoeDepth (ZoeD_N) at GFIE's 1920x1080 frames: input 384x672", (
              "python scripts/export_monodepth.py zoedepth --variant N --checkpoint ZoeD_M12_N.pt "
              "--image-size 1920x1080 --out models"),
              "depth.md", "Exporting ZoeDepth or Depth-Anything-V2-metric",
              "about 1.4 GB (ZoeD_N, BEiT-L backbone, not measured here)",
              "ONNX Runtime loads it: one float32 [1, 3, H, W] image input, a depth output; frames of "
              "another aspect fail, naming the size to export at"),
    ModelFile("gafa_view.onnx", "GAFA's GazeNet, 7-frame windows (view: gafa)",
              "python scripts/export_gafa_view.py --gafa dynamic-3d-gaze-from-afar --out models",
              "view.md", "GAFA's view network (`view: gafa`)",
              "tens of MB (two EfficientNet-b0 branches and LSTMs, not measured here)",
              "ONNX Runtime loads it: image, head_mask, body_dv of 7 frames in, gaze [B, 7, 3] out"),
)


def contract() -> dict[str, ModelFile]:
    """MODEL_FILES by file name."""
    return {f.name: f for f in MODEL_FILES}


def command_for(f: ModelFile, folder: Path | None = None) -> str:
    """The recipe's command writing into `folder` rather than `models`."""
    if folder is None:
        return f.make
    return " ".join({"models": str(folder), "models/": f"{folder}/"}.get(w, w) for w in f.make.split(" "))


def how_to_make(name: str, hint: str = "", folder: Path | None = None) -> str:
    """How to make the file `name` of the model folder: its recipe's command (writing into `folder`)
    and page, else `hint`."""
    f = contract().get(name)
    if f is None:
        return hint
    return f"{f.what}: `{command_for(f, folder)}` ({f.doc})"


def anchor(section: str) -> str:
    """GitHub's anchor of a section title."""
    return re.sub(r"[^\w\- ]", "", section.lower()).replace(" ", "-")


@dataclass
class FileStatus:
    """One model file a pipeline reads: where (the pipeline key), its path, and what check found."""

    key: str
    path: Path
    stage: str
    hint: str
    status: str = "missing"  # verified | present | failing | missing
    detail: str = ""
    pipelines: list[str] = field(default_factory=list)

    @property
    def make(self) -> str:
        return how_to_make(self.path.name, self.hint, self.path.parent)


def _size(path: Path) -> str:
    n = path.stat().st_size if path.is_file() else 0
    return "" if not n else f"{n / 1e6:.1f} MB" if n >= 1e5 else f"{n / 1e3:.1f} kB" if n >= 1e3 else f"{n} B"


def report(models: Path, files: list[FileStatus]) -> tuple[str, bool]:
    """The listing `models check` prints, and whether every file is verified."""
    lines = [f"model folder {models}"]
    for f in files:
        where = f.path.name if f.path.parent == models else str(f.path)
        lines.append(f"  {f.status:<9} {where:<26} {_size(f.path):>9}   {' '.join(f.pipelines)}")
        if f.status == "missing":
            lines.append(f"            {f.make}")
        elif f.detail:
            lines.append(f"            {f.detail}")
    counts = {s: sum(f.status == s for f in files) for s in ("verified", "present", "failing", "missing")}
    lines.append(", ".join(f"{n} {s}" for s, n in counts.items()))
    return "\n".join(lines), counts["verified"] == len(files)
