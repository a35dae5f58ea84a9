"""The package as `pip install` gives it: the wheel carries the pipelines and schemas it reads, and
its command runs a bundled pipeline from an empty folder in a fresh virtual environment where the
checkout's source cannot be imported (its dependencies come from this environment: a `.pth` line
naming its site-packages, whose own `.pth` files, the checkout's editable finder among them, are
not run)."""
import os
import re
import shutil
import subprocess
import sys
import sysconfig
import zipfile
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


@pytest.mark.slow
def test_the_wheel_runs_a_bundled_pipeline_outside_the_checkout(tmp_path):
    wheel = _build_wheel(tmp_path)
    names = set(zipfile.ZipFile(wheel).namelist())
    wanted = {f"ga3ce_prep/pipelines/{n}.yaml" for n in pipeline_names()}
    wanted |= {"ga3ce_prep/schemas/pipeline.schema.json", "ga3ce_prep/schemas/store.schema.json",
               "ga3ce_prep/synthetic/presets/transfer.yaml"}
    assert len(wanted) > 10 and not wanted - names, f"the wheel lacks {sorted(wanted - names)}"

    venv = tmp_path / "venv"
    _sh(sys.executable, "-m", "venv", "--without-pip", venv, cwd=tmp_path)
    python = venv / "bin" / "python"
    purelib = Path(_sh(python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])", cwd=tmp_path).strip())
    (purelib / "dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    _sh(sys.executable, "-m", "pip", "--python", python, "install", "--no-deps", "--no-index", "-q", wheel,
        cwd=tmp_path)

    empty = tmp_path / "empty"
    empty.mkdir()
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "GA3CE_", "VIRTUAL_ENV"))}
    env["PATH"] = f"{venv / 'bin'}{os.pathsep}{env.get('PATH', '')}"
    where = _sh(python, "-c", "import sys, ga3ce_prep; print(ga3ce_prep.__file__); "
                "print(any('editable' in repr(f).lower() for f in sys.meta_path))",
                cwd=empty, env=env).split()
    assert Path(where[0]).is_relative_to(venv) and where[1] == "False", where
    cli = venv / "bin" / "ga3ce-prep"
    assert _sh(cli, "--version", cwd=empty, env=env).strip() == f"ga3ce-prep, version {ga3ce_prep.__version__}"
    listed = re.sub(r"-\s+", "-", _sh(cli, "run", "--help", cwd=empty, env=env))  # wrapped at hyphens
    assert all(n in listed for n in pipeline_names()), listed

    every = _sh(python, "-c", "from ga3ce_prep.bundled import pipeline_names\n"
                "from ga3ce_prep.pipeline.config import load_pipeline\n"
                "for n in pipeline_names(): print(load_pipeline(n, '.', check_files=False).name)", cwd=empty, env=env)
    assert every.split() == pipeline_names()                               # each validates against the schema
    assert "--transfer-rooms" in _sh(cli, "demo", "--help", cwd=empty, env=env)
    _sh(cli, "synth", *WORLD, "--out", "world", "--quiet", cwd=empty, env=env)
    _sh(cli, "run", "--pipeline", "synthetic", "--data", "world", "--out", "s.zarr", "-q",
        "--set", "stages.objects.params.stride=1", cwd=empty, env=env)
    info = _sh(cli, "info", "s.zarr", cwd=empty, env=env)
    assert f"pipeline     synthetic ({purelib / 'ga3ce_prep' / 'pipelines' / 'synthetic.yaml'}" in info, info
    assert "frames       12 (of 12 in the dataset; 0 dropped)" in info, info
    assert "every one matches its SHA-256" in info, info
