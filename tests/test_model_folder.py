"""The model folder as a contract (ga3ce_prep/weights/folder.py, docs/models/README.md): the table is
what the paper's pipelines read from `{models}`; every recipe in docs/models/ and scripts/ writes
exactly those names; following the recipes with the tests' stand-in models gives a folder that
`ga3ce-prep models check` accepts; and `run` refuses a missing file naming the command that makes it."""
import re
import shlex
import subprocess
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from ga3ce_prep.cli import cli
from ga3ce_prep.errors import ModelFileError
from ga3ce_prep.files import file_sha256
from ga3ce_prep.pipeline import load_pipeline, run_pipeline
from ga3ce_prep.pipeline.config import stage_files
from ga3ce_prep.store import open_store
from ga3ce_prep.weights.cli import readers, table_markdown
from ga3ce_prep.weights.folder import MODEL_FILES, PAPER_PIPELINES, contract

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")  # torch 2.13 on TorchScript
REPO = Path(__file__).resolve().parents[1]
PAGES = REPO / "docs" / "models"


def _blocks(text: str) -> list[str]:
    """The fenced code blocks of a Markdown page, line continuations joined."""
    return [re.sub(r"\\\n\s*", "", b) for b in re.findall(r"```[a-z]*\n(.*?)```", text, flags=re.S)]


def _written(block: str) -> set[str]:
    """The model-folder files a recipe's `# -> models/...` lines name."""
    return {m for line in block.splitlines() if line.lstrip().startswith("# ->")
            for m in re.findall(r"(?<![\w/])models/([\w.-]+)", line)}


def test_the_table_is_every_file_the_paper_pipelines_read(tmp_path):
    read = readers()
    assert set(read) == set(contract()), "docs/models/README.md's table and the paper pipelines' {models} files differ"
    for name in PAPER_PIPELINES:
        conf = load_pipeline(name, tmp_path, check_files=False, models=tmp_path / "m")
        for sc in conf.stages.values():
            for f in stage_files(sc, tmp_path):
                assert f.path.parent == tmp_path / "m", f"{name}: {f.key} reads {f.path} outside the model folder"
    assert table_markdown() in (PAGES / "README.md").read_text(), \
        "docs/models/README.md's table is stale: print table_markdown() from ga3ce_prep/weights/cli.py"


def test_the_recipes_write_the_names_the_pipelines_read():
    """Each row's command is in its recipe's page and section, in a code block whose `# ->` line names
    the file; and every `# ->` line of docs/models/ and of scripts/ names only files the table has
    (or says that no bundled pipeline reads it)."""
    for f in MODEL_FILES:
        text = (PAGES / f.page).read_text()
        heading = re.search(rf"^#+ {re.escape(f.section)}$", text, flags=re.M)
        assert heading, f"{f.page} has no section {f.section!r}"
        section = re.split(r"^## ", text[heading.end():], flags=re.M)[0]
        blocks = [b for b in _blocks(section) if f.make in " ".join(b.split())]
        assert blocks, f"{f.page}, {f.section!r}: no code block runs `{f.make}`"
        assert any(f.name in _written(b) for b in blocks), f"{f.page}: its recipe does not say it writes {f.name}"
    sources = [(p, "\n".join(_blocks(p.read_text()))) for p in PAGES.glob("*.md")]
    sources += [(p, p.read_text()) for p in (REPO / "scripts").glob("export_*.py")]
    for path, text in sources:
        for line in text.splitlines():
            if line.lstrip().startswith("# ->") and "no bundled pipeline reads it" not in line:
                stray = set(re.findall(r"(?<![\w/])models/([\w./-]+?)[,)\s]", line + " ")) - set(contract())
                assert not stray, f"{path.relative_to(REPO)}: `{line.strip()}` writes {stray}: no pipeline reads it"


def _script(name: str):
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, REPO / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _follow(command: str, stand_ins: dict, monkeypatch) -> None:
    """Run one recipe's command as written, in the current folder; only the authors' code each
    script imports is replaced by a stand-in model (`stand_ins`: script -> (loader name, loader))."""
    argv = shlex.split(command)
    if argv[0] == "ga3ce-prep":
        res = CliRunner().invoke(cli, argv[1:], catch_exceptions=False)
        assert res.exit_code == 0, res.output
    elif argv[0] == "python":
        name = Path(argv[1]).stem
        script = _script(name)
        loader, stand_in = stand_ins[name]
        monkeypatch.setattr(script, loader, stand_in(script))
        script.main(argv[2:])
    else:
        subprocess.run(["bash", "-c", command], check=True)


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::UserWarning", "ignore::torch.jit.TracerWarning")  # the exporters' notes
def test_following_the_recipes_with_stand_in_models_gives_a_folder_models_check_accepts(tmp_path, monkeypatch,
                                                                                        synth_world):
    import torch

    from ga3ce_prep.skeleton import JOINT_NAMES
    from ga3ce_prep.testing import mobilesam_random, paper_models

    monkeypatch.chdir(tmp_path)
    # the recipes' inputs: MobileSAM's checkpoint (the tests' random weights) and GFIE's checkpoint
    (tmp_path / "weights").mkdir()
    (tmp_path / "weights" / "mobile_sam.pt").symlink_to(mobilesam_random.checkpoint())
    torch.save(paper_models.gfie_checkpoint(paper_models.gfie_state(paper_models.random_gfie_net())),
               tmp_path / "gfiemodel.pt.tar")
    # ... and in place of the authors' code the scripts import, stand-ins of the same call convention
    stand_ins = {
        "export_crop_pose": ("load_metrabs", lambda s: lambda model_dir: (
            paper_models.Constant(paper_models.constant_joints()), 64, list(JOINT_NAMES))),
        "export_monodepth": ("load_zoedepth", lambda s: lambda variant, checkpoint: s.metric_module(
            lambda m, x: m(x))(paper_models.StandInDepth()).eval()),
        "export_gafa_view": ("load_gazenet", lambda s: lambda gafa, checkpoint, unsafe=False: s.GazeOnly(
            paper_models.StandInGazeNet()).eval()),
    }
    for command in dict.fromkeys(f.make for f in MODEL_FILES):   # each once, in the table's order
        _follow(command, stand_ins, monkeypatch)
    assert sorted(p.name for p in (tmp_path / "models").iterdir()) == sorted(contract())

    for name in ("gfie", "cad120", "gafa"):
        res = CliRunner().invoke(cli, ["models", "check", "--models", "models", "--pipeline", name])
        assert res.exit_code == 0, res.output
        listed = [line.split() for line in res.output.splitlines() if line.startswith("  ")]
        assert listed and all(row[0] == "verified" for row in listed), res.output
        assert {row[1] for row in listed} == {f for f, ps in readers().items() if name in ps}
    load_pipeline("gafa", tmp_path, models="models")  # the run's own check before any work accepts it too
    # and `run` itself, on two frames of the tests' GFIE-format world
    args = ["run", "-p", "gfie", "-d", str(synth_world), "-o", "s.zarr", "--models", "models", "--limit", "2", "-q",
            "--set", "stages.objects.params.points_per_side=4"]
    res = CliRunner().invoke(cli, args, catch_exceptions=False)
    assert res.exit_code == 0, res.output
    store = open_store("s.zarr")
    assert len(store) == 2 and np.isfinite(store.frames["pose"]).all() and np.isfinite(store.frames["view"]).all()
    assert list(store.attrs["stages"]["view"]["models"].values()) == [file_sha256("models/gfiemodel.pt.tar")]


def test_models_check_and_run_name_each_missing_file_and_its_command(tmp_path, monkeypatch):
    from ga3ce_prep.testing.paper_models import write_paper_models

    models = tmp_path / "models"
    write_paper_models(models)
    (models / "gfiemodel.pt.tar").unlink()
    (models / "metrabs.joints.txt").unlink()
    (models / "gafa_view.onnx").write_bytes(b"not a model")
    res = CliRunner().invoke(cli, ["models", "check", "--models", str(models)])
    assert isinstance(res.exception, ModelFileError), res.output           # ga3ce-prep: error, exit 2
    out = res.output
    assert re.search(r"^  missing +gfiemodel.pt.tar +gfie cad120 gfie-monodepth$", out, flags=re.M), out
    assert f"`cp gfiemodel.pt.tar {models}/`" in out and "docs/models/view.md" in out
    assert re.search(r"^  present +metrabs.pt .* gfie cad120 gfie-monodepth\n +not checked: metrabs.joints.txt missing",
                     out, flags=re.M), out
    assert f"--out {models}`" in out.split("metrabs.joints.txt", 2)[2]
    assert re.search(r"^  failing +gafa_view.onnx .*\n +.*gafa_view.onnx", out, flags=re.M), out
    assert re.search(r"^  verified +mobile_sam_encoder.onnx", out, flags=re.M), out
    assert "3 verified, 2 present, 1 failing, 2 missing" in out

    monkeypatch.setenv("GA3CE_MODEL_DIR", str(models))
    with pytest.raises(ModelFileError) as e:
        run_pipeline("gfie", tmp_path, tmp_path / "s.zarr", progress=False)
    lines = str(e.value).splitlines()
    assert re.match(r"stages.pose \(joint names\): model file .*metrabs.joints.txt does not exist; .*"
                    rf"`python scripts/export_crop_pose.py metrabs .* --out {models}`", lines[0]), lines
    assert re.match(r"  stages.view.params.checkpoint: model file .*gfiemodel.pt.tar does not exist; GFIE's released "
                    r"checkpoint", lines[1]), lines
    assert lines[2] == f"  `ga3ce-prep models check --models {models} --pipeline gfie` lists what the folder holds"
    assert len(lines) == 3 and not (tmp_path / "s.zarr").exists()
