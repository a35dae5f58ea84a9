"""The package as `pip install` gives it: the wheel carries the pipelines and schemas it reads, and
its command runs a bundled pipeline from an empty folder in a fresh virtual environment where the
checkout's source cannot be imported (its dependencies come from this environment: a `.pth` line
naming its site-packages, whose own `.pth` files, the checkout's editable finder among them, are
not run)."""
import json
import os
import re
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from dataclasses import dataclass
from pathlib import Path

import pytest

import ga3ce_prep
from ga3ce_prep.bundled import pipeline_names

REPO = Path(__file__).resolve().parents[1]
# a tiny GFIE-format world: 3 rooms x 4 frames at 160x120 (testing/worlds.py SMALL_WORLD, SMALL)
WORLD = ["--format", "gfie", "--scenes", "3", "--frames-per-scene", "4", "--seed", "5", "--width", "160"]


def _sh(*args: str | Path, cwd: Path, env: dict[str, str] | None = None) -> str:
    p = subprocess.run([str(a) for a in args], cwd=cwd, env=env, capture_output=True, text=True, timeout=300)
    command = " ".join(map(str, args))
    assert p.returncode == 0, f"{command} exited {p.returncode}:\n{p.stdout[-3000:]}\n{p.stderr[-3000:]}"
    return p.stdout


def _build_wheel(tmp: Path) -> Path:
    """The wheel of a copy of the source (no build folder left in the checkout; no network)."""
    src = tmp / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy(REPO / name, src / name)
    shutil.copytree(REPO / "ga3ce_prep", src / "ga3ce_prep", ignore=shutil.ignore_patterns("__pycache__"))
    _sh(sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index", "-q",
        "-w", tmp / "dist", src, cwd=tmp)
    (wheel,) = (tmp / "dist").glob("ga3ce_prep-*.whl")
    return wheel


@dataclass(frozen=True)
class Installed:
    """The wheel installed in a fresh virtual environment, and an empty folder outside the checkout."""

    wheel: Path
    venv: Path
    purelib: Path
    empty: Path
    env: dict[str, str]

    @property
    def python(self) -> Path:
        return self.venv / "bin" / "python"

    def cli(self, *args: str | Path, cwd: Path | None = None) -> str:
        """`ga3ce-prep ARGS` from the empty folder (or cwd); returns its stdout."""
        return _sh(self.venv / "bin" / "ga3ce-prep", *args, cwd=cwd or self.empty, env=self.env)


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> Installed:
    tmp = tmp_path_factory.mktemp("wheel")
    wheel = _build_wheel(tmp)
    venv = tmp / "venv"
    _sh(sys.executable, "-m", "venv", "--without-pip", venv, cwd=tmp)
    python = venv / "bin" / "python"
    purelib = Path(_sh(python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])", cwd=tmp).strip())
    (purelib / "dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    _sh(sys.executable, "-m", "pip", "--python", python, "install", "--no-deps", "--no-index", "-q", wheel, cwd=tmp)
    empty = tmp / "empty"
    empty.mkdir()
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "GA3CE_", "VIRTUAL_ENV"))}
    env["PATH"] = f"{venv / 'bin'}{os.pathsep}{env.get('PATH', '')}"
    return Installed(wheel, venv, purelib, empty, env)


@pytest.mark.slow
def test_the_wheel_runs_a_bundled_pipeline_outside_the_checkout(installed):
    names = set(zipfile.ZipFile(installed.wheel).namelist())
    wanted = {f"ga3ce_prep/pipelines/{n}.yaml" for n in pipeline_names()}
    wanted |= {"ga3ce_prep/schemas/pipeline.schema.json", "ga3ce_prep/schemas/store.schema.json",
               "ga3ce_prep/synthetic/presets/transfer.yaml"}
    assert len(wanted) > 10 and not wanted - names, f"the wheel lacks {sorted(wanted - names)}"

    venv, python, empty, env = installed.venv, installed.python, installed.empty, installed.env
    where = _sh(python, "-c", "import sys, ga3ce_prep; print(ga3ce_prep.__file__); "
                "print(any('editable' in repr(f).lower() for f in sys.meta_path))",
                cwd=empty, env=env).split()
    assert Path(where[0]).is_relative_to(venv) and where[1] == "False", where
    assert installed.cli("--version").strip() == f"ga3ce-prep, version {ga3ce_prep.__version__}"
    listed = re.sub(r"-\s+", "-", installed.cli("run", "--help"))  # wrapped at hyphens
    assert all(n in listed for n in pipeline_names()), listed

    every = _sh(python, "-c", "from ga3ce_prep.bundled import pipeline_names\n"
                "from ga3ce_prep.pipeline.config import load_pipeline\n"
                "for n in pipeline_names(): print(load_pipeline(n, '.', check_files=False).name)", cwd=empty, env=env)
    assert every.split() == pipeline_names()                               # each validates against the schema
    installed.cli("synth", *WORLD, "--out", "world", "--quiet")
    installed.cli("run", "--pipeline", "synthetic", "--data", "world", "--out", "s.zarr", "-q",
                  "--set", "stages.objects.params.stride=1")
    info = installed.cli("info", "s.zarr")
    assert f"pipeline     synthetic ({installed.purelib / 'ga3ce_prep' / 'pipelines' / 'synthetic.yaml'}" in info, info
    assert "frames       12 (of 12 in the dataset; 0 dropped)" in info, info
    assert "every one matches its SHA-256" in info, info


# runs every bundled pipeline in one process of the installed package (one import of torch), through
# its command line; prints ROW, then name, frames kept, frames failed and the pipeline file the store names
EVERY = """
import json, sys
from pathlib import Path
from ga3ce_prep.cli import cli
from ga3ce_prep.store import open_store
from ga3ce_prep.testing.bundled_runs import bundled_runs

root = Path(sys.argv[1])
for run in bundled_runs(root / "inputs"):
    out = root / f"{run.name}.zarr"
    cli.main(run.args(out), prog_name="ga3ce-prep", standalone_mode=False)
    s = open_store(out)
    failed = len(set(s.failures["frame_id"].tolist()))
    print("ROW", json.dumps([run.name, run.frames, len(s), failed, s.attrs["pipeline"]["file"]]))
"""


@pytest.mark.slow
def test_every_bundled_pipeline_runs_from_the_wheel(installed):
    """Each bundled name, from the installed package only, on a tiny world of its format with the
    tests' stand-in model folder (testing/bundled_runs.py): its first frames, every one kept except where
    the pipeline drops frames by design (GAFA's 7-frame windows) or its real models find no person in
    a 160x120 synthetic frame (folder-real's registry pose and face models)."""
    (installed.empty.parent / "every.py").write_text(EVERY)
    out = _sh(installed.python, installed.empty.parent / "every.py", "every", cwd=installed.empty,
              env=installed.env)
    rows = {r[0]: r[1:] for r in (json.loads(line[4:]) for line in out.splitlines() if line.startswith("ROW "))}
    assert list(rows) == pipeline_names()
    for name, (frames, kept, failed, file) in rows.items():
        assert file == str(installed.purelib / "ga3ce_prep" / "pipelines" / f"{name}.yaml"), (name, file)
        assert kept + failed == frames, (name, frames, kept, failed)
        assert kept == frames or name in ("gafa", "folder-real"), (name, frames, kept, failed)
    assert rows["gafa"][1] > 0


@pytest.mark.slow
def test_the_demo_runs_from_the_wheel(installed):
    """`ga3ce-prep demo` from an empty folder, on worlds small enough for a test: the whole chain,
    its table and the line that says whether the paper's GA3CE beats its no-objects ablation."""
    out = installed.cli("demo", "--rooms", "3", "--sessions-per-room", "3", "--frames-per-session", "2",
                        "--transfer-rooms", "1", "--epochs", "1", "--out", "demo")
    assert "[5/5] evaluation on the transfer world" in out, out
    table = out.split("3D MAE (deg)", 1)[1].splitlines()
    assert len(table) > 5 and table[0].split() == ["seen", "rooms", "transfer"], table
    for line in table[1:5]:                                              # four rows, two finite figures each
        seen, transfer = map(float, line.split()[-2:])
        assert 0 < seen < 180 and 0 < transfer < 180, line
    assert "its no-objects ablation on the seen rooms here" in out
    assert (installed.empty / "demo" / "runs" / "demo" / "calibrated" / "full" / "seed0" / "best.pt").is_file()
