"""The repository as a stranger meets it: a short README whose file map is complete and whose
figures link to their studies, relative links that resolve, and no file that names a build
machine's paths, the team's sibling folder or an issue tracker's numbers."""
import json
import re
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
README = (REPO / "README.md").read_text()


def tracked_files() -> list[Path]:
    """The files git tracks (the repository as a clone has it); the working tree if git is absent."""
    try:
        out = subprocess.run(["git", "ls-files"], cwd=REPO, capture_output=True, text=True, check=True).stdout
        return [REPO / f for f in out.splitlines() if (REPO / f).is_file()]
    except (OSError, subprocess.CalledProcessError):
        return [p for p in REPO.rglob("*") if p.is_file() and ".venv" not in p.parts and ".git" not in p.parts]


def text_files() -> list[Path]:
    return [p for p in tracked_files() if p.suffix in {".py", ".md", ".yaml", ".toml", ".sh", ".json", ".txt", ""}]


def test_readme_is_short():
    assert len(README.splitlines()) <= 150


def test_readme_map_names_every_folder_and_make_target():
    folders = sorted(p.name for p in REPO.iterdir() if p.is_dir() and not p.name.startswith((".", "_"))
                     and any(True for _ in p.iterdir()) and p.name not in {"out", "runs", "build"}
                     and not p.name.endswith(".egg-info"))
    folders += [".ci"]
    packages = sorted(p.name for p in (REPO / "ga3ce_prep").iterdir() if (p / "__init__.py").is_file())
    targets = re.findall(r"^([a-z][a-z0-9-]*):", (REPO / "Makefile").read_text(), flags=re.M)
    assert {"demo", "test", "lint"} <= set(targets)
    missing = [f"{f}/" for f in folders if f"{f}/" not in README]
    missing += [f"ga3ce_prep/{p}/" for p in packages if f"{p}/" not in README]
    missing += [f"make {t}" for t in targets if f"make {t}" not in README]
    assert not missing, f"README.md's file map does not name: {missing}"


def test_readme_figures_link_to_studies():
    """Every row of the headline table links to the docs/studies/ page that measured it."""
    start = README.index("## Headline figures")
    table = [line for line in README[start:].split("\n## ")[0].splitlines() if line.startswith("|")][2:]
    assert 1 <= len(table) <= 12
    for row in table:
        assert "docs/studies/" in row, f"headline row without its study: {row}"


FIGURE = re.compile(r"(?<![\w.#/-])(\d+\.\d+|\d+(?=%))")        # a decimal, or a whole percentage
STUDY_LINK = re.compile(r"\((docs/studies/[\w.-]+\.md)(?:#[\w-]+)?\)")


def readme_figures() -> list[tuple[str, list[str], list[str]]]:
    """(text, its figures, the studies it links) for each README paragraph and table row with a figure;
    a table row without a link of its own takes the links of the paragraph before its table."""
    out, before = [], []
    for block in re.split(r"\n\s*\n", re.sub(r"```.*?```", "", README, flags=re.S)):
        table = block.lstrip().startswith("|")
        for unit in block.splitlines() if table else [block]:
            links = STUDY_LINK.findall(unit) or (before if table else [])
            figures = FIGURE.findall(STUDY_LINK.sub("", unit))
            if figures:
                out.append((unit, figures, links))
        if not table:
            before = STUDY_LINK.findall(block)
    return out


RESULTS_LINK = re.compile(r"\]\((results/[\w.-]+\.json)\)")


def study_text(link: str) -> str:
    """A study page's text and, for each results file it links (docs/studies/results/*.json, an
    experiment's results), that file's tables as `experiment show` prints them."""
    from ga3ce_prep.experiments import format_results

    page = REPO / link
    text = page.read_text()
    for rel in RESULTS_LINK.findall(text):
        text += "\n" + format_results(json.loads((page.parent / rel).read_text()))
    return text


def test_readme_figures_are_in_their_studies():
    """Each figure of the README (its tables, the headline rows, its paragraphs) is written in a study
    the row or paragraph links, or in a results file that study links: a figure is quoted, never
    computed or remembered."""
    rows = readme_figures()
    assert len(rows) >= 10
    bad = []
    for unit, figures, links in rows:
        assert links, f"README figures without a study: {unit[:100]}"
        text = " ".join(study_text(link) for link in set(links))
        bad += [f"{f} ({unit[:60]}...)" for f in figures if f not in text]
    assert not bad, "README figures not in the studies they link:\n" + "\n".join(bad)


def test_results_files_that_studies_link_are_experiments():
    for page in sorted((REPO / "docs" / "studies").glob("*.md")):
        for rel in RESULTS_LINK.findall(page.read_text()):
            r = json.loads((page.parent / rel).read_text())
            assert {"experiment", "code", "machine", "worlds", "arms", "scores"} <= set(r), (page.name, rel)
            assert r["code"]["commit"] and not r["code"]["dirty"], f"{rel}: results of uncommitted code"


def test_a_study_with_results_takes_its_tables_from_them():
    """A study that links an experiment's results file takes the figures of its tables from that
    file (as `experiment show` prints them), not from memory or another run."""
    from ga3ce_prep.experiments import format_results

    pages = [p for p in sorted((REPO / "docs" / "studies").glob("*.md")) if RESULTS_LINK.search(p.read_text())]
    assert pages
    for page in pages:
        text = page.read_text()
        printed = "\n".join(format_results(json.loads((page.parent / rel).read_text()))
                            for rel in RESULTS_LINK.findall(text))
        rows = [line for line in re.sub(r"```.*?```", "", text, flags=re.S).splitlines() if line.startswith("|")]
        bad = [f"{f} in {row[:60]}" for row in rows for f in FIGURE.findall(STUDY_LINK.sub("", row))
               if f not in printed]
        assert not bad, f"{page.name}: table figures not in its results files:\n" + "\n".join(bad)


def test_the_figure_rule_can_fail():
    assert FIGURE.findall("15.97 / 15.60, 53% and 1.97x; v2.0 x2.5") == ["15.97", "15.60", "53", "1.97"]


@pytest.mark.parametrize("path", [p for p in tracked_files() if p.suffix == ".md"], ids=lambda p: p.name)
def test_relative_links_resolve(path):
    text = re.sub(r"```.*?```", "", path.read_text(), flags=re.S)
    for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text):
        if re.match(r"[a-z]+:", target):
            continue
        assert (path.parent / target).exists(), f"{path.relative_to(REPO)}: link to {target} does not resolve"


def test_studies_are_dated_and_reproducible():
    studies = sorted((REPO / "docs" / "studies").glob("*.md"))
    assert studies
    for p in studies:
        if p.name == "README.md":
            continue
        assert re.match(r"\d{4}-\d{2}-\d{2}-[a-z0-9-]+\.md$", p.name), p.name
        text = p.read_text()
        assert re.search(r"python|pytest |make |ga3ce-prep ", text), f"{p.name} gives no command that reproduces it"


# A build machine's absolute paths (a workflow lock's among them) and the team's sibling folder.
MACHINE = re.compile(r"(?<![\w.])/(?:work|root|home|tmp)/[\w.-]|\.\./shared\b")
# Our tracker's issue numbers in prose ("issue 16", "issues 16 and 17"); another project's
# issues are named with the project ("ZoeDepth's issue tracker").
ISSUE = re.compile(r"\bissues? #?\d+|\(#\d+\)", re.I)


def test_no_machine_paths_or_issue_numbers():
    here = Path(__file__).resolve()
    bad = []
    for p in text_files():
        if p.resolve() == here:
            continue
        for n, line in enumerate(p.read_text(errors="replace").splitlines(), 1):
            if MACHINE.search(line) or ISSUE.search(line):
                bad.append(f"{p.relative_to(REPO)}:{n}: {line.strip()[:100]}")
    assert not bad, "\n".join(bad[:30])
