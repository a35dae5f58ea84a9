"""Every pointer resolves: the sections and anchors that code, `--help` texts, pipelines, schemas and
docs cite exist; the files and modules they name exist; every figure in the README and the reference
pages links the study that measured it; every study names the commit it measured and is in the
studies index as current or superseded by another.

What counts as a citation (in Python: string literals, adjacent ones joined, and comments, lines
joined; elsewhere the text, with wrapped lines joined):
- `docs/X.md "Section"` (also `docs/X.md, "Section"`, `("Section")`): a heading of X, or a bold
  run-in label (`**Section.**` at a paragraph's start), is the section or starts with it followed by
  ":", ",", " (" or " -"; backticks and a leading "2." numbering do not count;
- `docs/X.md#anchor` and a markdown link `(X.md#anchor)`: GitHub's slug of one of X's headings;
- `docs/X.md §N`: a heading numbered "N.";
- a path `docs/...md`, `ga3ce_prep/...`, `benchmarks/...`, `tests/...`, `pipelines/...`,
  `schemas/...`: that file or folder (a module path also as `.py`).

What counts as a figure: a paragraph, list item or table row of README.md, docs/*.md or
docs/models/*.md (code blocks left out) with a measured quantity (`MEASURED`): a time per unit
("0.5 s a frame", "1 ms per MB", any milliseconds), a time on N cores, a speed-up ("4x faster",
"about 11x"), a rate ("195 samples/s"), a decimal angle ("9.66°") or a decimal percentage. It must
link a study page (docs/studies/<date>-<name>.md), in the block or, for a table row, in the
paragraph that introduces the table; a figure the test suite asserts may cite that test
(tests/test_*.py) instead. `NOT_FIGURES` lists the few specifications that read like figures.
"""
from __future__ import annotations

import ast
import io
import re
import subprocess
import tokenize
import unicodedata
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"
STUDIES = DOCS / "studies"
PIPELINES = REPO / "ga3ce_prep" / "pipelines"
SKIP_DIRS = {".git", ".venv", "out", "build", "runs", "node_modules", "__pycache__", ".ruff_cache", ".mypy_cache",
             ".pytest_cache"}
FENCE = re.compile(r"^(```|~~~).*?^\1", re.M | re.S)


# --- the text a file shows its readers ------------------------------------------------------------

def python_text(path: Path) -> str:
    """A Python file's string literals (adjacent ones joined, as Python joins them) and comments
    (consecutive comment lines joined), one per line, whitespace collapsed."""
    out: list[str] = []
    strings: list[str] = []
    comments: list[str] = []

    def flush() -> None:
        if strings:
            out.append("".join(strings))
            strings.clear()
        if comments:
            out.append(" ".join(comments))
            comments.clear()

    for tok in tokenize.generate_tokens(io.StringIO(path.read_text()).readline):
        if tok.type == tokenize.STRING:
            if comments:
                flush()
            try:
                value = ast.literal_eval(tok.string)
            except (ValueError, SyntaxError):   # an f-string: its text, the fields left as written
                value = re.sub(r"^[a-zA-Z]*(\"\"\"|'''|\"|')|(\"\"\"|'''|\"|')$", "", tok.string)
            strings.append(value if isinstance(value, str) else "")
        elif tok.type == tokenize.COMMENT:
            if strings:
                flush()
            comments.append(tok.string.lstrip("#").strip())
        elif tok.type in (tokenize.NL, tokenize.NEWLINE, tokenize.INDENT, tokenize.DEDENT) or (
                tok.type == tokenize.OP and tok.string in "()" and strings):
            continue
        else:
            flush()
    flush()
    return "\n".join(" ".join(t.split()) for t in out)


def reader_text(path: Path) -> str:
    """The text a reader sees in `path`, lines a citation may wrap across joined."""
    if path.suffix == ".py":
        return python_text(path)
    text = path.read_text(errors="replace")
    if path.suffix == ".md":
        text = FENCE.sub(lambda m: "\n" * m.group(0).count("\n"), text)
        return re.sub(r"(?<!\n)\n(?![\n|#])[ \t]*", " ", text)   # a paragraph's lines, not tables or headings
    if path.suffix == ".json":
        return text.replace('\\"', '"')
    return re.sub(r"\n[ \t]*#+[ \t]*", " ", text)   # YAML, shell, Makefile: comment lines joined


def scanned_files() -> list[Path]:
    """Code, help texts, pipelines, schemas, scripts and docs: every file that points at docs."""
    out = []
    for p in sorted(REPO.rglob("*")):
        rel = p.relative_to(REPO)
        if any(part in SKIP_DIRS or part.endswith(".egg-info") for part in rel.parts) or not p.is_file():
            continue
        if p.suffix in (".py", ".md", ".yaml", ".yml", ".json", ".toml", ".sh") or p.name in ("Makefile", "run"):
            if p != Path(__file__).resolve():
                out.append(p)
    return out


FILES = scanned_files()


# --- headings, anchors, sections --------------------------------------------------------------------

def headings(md: str) -> list[str]:
    return [m.group(1).strip().rstrip("#").strip() for m in re.finditer(r"^#{1,6}\s+(.+)$", FENCE.sub("", md), re.M)]


def labels(md: str) -> list[str]:
    """Bold run-in paragraph labels: `**Object storage.** ...`, `- **Damaged cache entries** ...`."""
    return [m.group(1).rstrip(".").strip()
            for m in re.finditer(r"^(?:[-*] )?\*\*([^*\n]+?)\*\*", FENCE.sub("", md), re.M)]


def plain(text: str) -> str:
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", text)
    return text.replace("`", "").replace("’", "'").replace("*", "").strip()


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation but '-' and '_' dropped, spaces to '-'."""
    s = plain(heading).lower()
    return "".join(c for c in s if c in " -_" or unicodedata.category(c)[0] in "LMN").replace(" ", "-")


def anchors(md: str) -> set[str]:
    seen: dict[str, int] = {}
    out = set()
    for h in headings(md):
        s = slug(h)
        out.add(s if s not in seen else f"{s}-{seen[s]}")
        seen[s] = seen.get(s, 0) + 1
    return out


def has_section(md: str, cited: str) -> bool:
    want = plain(cited).rstrip(".")
    for h in [*map(plain, headings(md)), *labels(md)]:
        for name in (h, re.sub(r"^\d+(\.\d+)*\.?\s+", "", h)):
            if name == want or (name.startswith(want) and re.match(r"(:|,| \(| -| —)", name[len(want):])):
                return True
    return False


CITE = re.compile(r"(?<![\w/.-])((?:\.\./)*(?:docs/)?[\w./-]*?[\w-]+\.md)"
                  r"(?:#([\w-]+)|[,:]?[ \t]*\(?[ \t]*[\"“]([^\"”\n]{2,80})[\"”]|\)?[ \t]*§[ \t]*(\d+))")
PATH = re.compile(r"(?<![\w/.:-])((?:docs|ga3ce_prep|benchmarks|tests|pipelines|schemas)/[\w./*-]*[\w/*])(?:::[\w.]+)?")
EXTERNAL = {"docs/API.md", "docs/INFERENCE.md"}   # isarandi/metrabs's files, which docs/paper.md names


def target(src: Path, name: str) -> Path | None:
    for base in ([REPO] if name.startswith("docs/") else []) + [src.parent, DOCS]:
        p = (base / name).resolve()
        if p.is_file():
            return p
    return None


def test_cited_sections_and_anchors_exist():
    bad, n = [], 0
    for path in FILES:
        for m in CITE.finditer(reader_text(path)):
            name, anchor, section, number = m.groups()
            if "docs/" not in name and path.suffix != ".md":   # another project's file (its README.md)
                continue
            n += 1
            where = f"{path.relative_to(REPO)}: {name}"
            md_path = target(path, name)
            if md_path is None:
                bad.append(f"{where}: no such file")
                continue
            md = md_path.read_text()
            if anchor and anchor not in anchors(md):
                bad.append(f"{where}#{anchor}: no heading has that anchor")
            if section and not has_section(md, section):
                bad.append(f'{where} "{section}": no such heading or paragraph label')
            if number and not any(re.match(rf"{number}\.\s", plain(h)) for h in headings(md)):
                bad.append(f"{where} §{number}: no section numbered {number}")
    assert n > 100, f"only {n} citations found: is the scan still reading the files?"
    assert not bad, "pointers that lead nowhere:\n" + "\n".join(bad)


def test_named_paths_exist():
    """Paths to the repository's own files in code, help texts, pipelines and docs (a pipeline
    file now lives in the package: ga3ce_prep/pipelines/NAME.yaml)."""
    bad = []
    for path in FILES:
        for m in PATH.finditer(reader_text(path)):
            name = m.group(1).rstrip("./")
            if any(c in name for c in "*<{") or name in EXTERNAL:
                continue
            if not any((base / cand).exists() for base in (REPO, path.parent)
                       for cand in (name, name + ".py")):
                bad.append(f"{path.relative_to(REPO)}: {m.group(0)}")
    assert not bad, "paths that do not exist:\n" + "\n".join(bad)


def test_every_bundled_pipeline_is_in_the_pipeline_table():
    names = sorted(p.stem for p in PIPELINES.glob("*.yaml"))
    assert "synthetic" in names and "folder-real" in names, names
    table = "\n".join(line for line in (DOCS / "pipeline.md").read_text().splitlines() if line.startswith("| `"))
    missing = [n for n in names if f"`{n}`" not in table]
    assert not missing, f"docs/pipeline.md's pipeline table leaves out {missing}"


def test_module_lists_name_the_modules():
    """A docs paragraph "Code: `ga3ce_prep/PKG/`, one module per concept: `a` (...), `b`, ..." names
    exactly PKG's modules (parenthesised names are functions or notes, not modules)."""
    checked = 0
    for md in sorted(DOCS.glob("*.md")):
        for m in re.finditer(r"Code: `ga3ce_prep/([\w/]+)/`, one module per concept:(.*?)(?:\n\n|$)",
                             md.read_text(), re.S):
            pkg = REPO / "ga3ce_prep" / m.group(1)
            listed = re.sub(r"\([^()]*\)", "", m.group(2))
            named = {n for n in re.findall(r"`([\w.]+)`", listed)}
            modules = {p.stem for p in pkg.glob("*.py") if p.stem != "__init__"}
            assert named == modules, (f"{md.name}: named but not modules: {sorted(named - modules)}; "
                                      f"modules not named: {sorted(modules - named)}")
            checked += 1
    assert checked


# --- figures ----------------------------------------------------------------------------------------

N = r"\d+(?:[.,]\d+)?"
R = rf"{N}(?:\s?[-–]\s?{N})?"
MEASURED = re.compile("|".join(f"(?:{m})" for m in (
    rf"{R}\s?(?:ms|s|min|minutes|h|hours)\b,?\s(?:per|a|an|each)\s(?:frame|photo|image|epoch|step|MB|GB|shard|"
    r"sequence|prompt|batch|window|run|store)\b",
    rf"{R}\s?(?:ms|s|min|minutes|h|hours)\b\s(?:on|with)\s(?:\d+|one|two)\s(?:cores?|threads?|CPUs?|workers?)",
    rf"{R}\s?ms\b",
    rf"{R}\s?(?:s|min|h)\s(?:vs|instead of|against)\s{N}",
    rf"{R}\s?(?:×|x)\s(?:faster|slower)\b",
    rf"(?:about|at|is|runs?)\s{N}\s?(?:×|x)\b(?!\s?\d)",
    rf"{N}\s?(?:×|x)\s(?:fewer|more|less)\b",
    rf"{R}\s?(?:frames|samples|images|steps)/s\b",
    rf"{N}\.\d+\s?°",
    rf"{N}\.\d+\s?%",
)))
BACKING = re.compile(r"studies/\d{4}-\d{2}-\d{2}-[\w-]+\.md|tests/test_\w+\.py")
# (page, phrase): specifications that read like figures
NOT_FIGURES = {
    ("docs/synthetic.md", "15 frames/s"),          # the synthetic GAFA-format world's frame rate
    ("docs/models/view.md", "about 3x"),           # how far a head box is downscaled before aliasing
}
REFERENCE_PAGES = [REPO / "README.md", *sorted(DOCS.glob("*.md")), *sorted((DOCS / "models").glob("*.md"))]


def blocks(md: str) -> list[tuple[int, str]]:
    """(line, text) of each paragraph, list item and table row (a row with its table's introducing
    paragraph), code blocks left out."""
    lines = FENCE.sub(lambda m: "\n" * m.group(0).count("\n"), md).split("\n")
    out: list[tuple[int, str]] = []
    cur: list[str] = []
    start, caption = 0, ""
    for i, line in enumerate(lines, 1):
        new_item = bool(re.match(r"\s{0,3}(?:[-*]|\d+\.)\s", line))
        if cur and (line.startswith(("|", "#")) or not line.strip() or new_item):
            out.append((start, " ".join(cur)))
            caption, cur = " ".join(cur), []
        if line.startswith("#"):
            caption = ""
        if line.startswith("|"):
            out.append((i, f"{line} {caption}"))
        elif line.strip() and not line.startswith("#"):
            start = start if cur else i
            cur.append(line.strip())
    if cur:
        out.append((start, " ".join(cur)))
    return out


@pytest.mark.parametrize("page", REFERENCE_PAGES, ids=lambda p: str(p.relative_to(REPO)))
def test_every_figure_links_its_study(page):
    rel = str(page.relative_to(REPO))
    bad = []
    for line, text in blocks(page.read_text()):
        found = [m.group(0) for m in MEASURED.finditer(text) if (rel, m.group(0)) not in NOT_FIGURES]
        if found and not BACKING.search(text):
            bad.append(f"{rel}:{line}: {found} in \"{text[:100]}...\"")
        for ref in BACKING.findall(text):
            assert (page.parent / ref).exists() or (REPO / ref).exists() or (DOCS / ref).exists(), f"{rel}: {ref}"
    assert not bad, "figures without a study:\n" + "\n".join(bad)


def test_the_figure_rule_catches_figures():
    """The rule fails where it should: a bare figure, and passes it with a study link."""
    assert MEASURED.search("the heatmap passes take about 0.65 s per frame")
    assert MEASURED.search("Checking the CRC costs about 1 ms per MB read")
    assert MEASURED.search("24 s on 2 cores, 3.5 s with --fast")
    assert MEASURED.search("bucketed: 195 samples/s") and MEASURED.search("10.97° / 9.66°")
    assert not MEASURED.search("a window of 0.2, then 0.5, then 1.0 x the box's shorter side (1920 x 1080)")
    study = "[study](studies/2026-11-29-scale-out.md)"
    rows = [t for _, t in blocks(f"Intro, {study}:\n\n| a | b |\n| --- | --- |\n| x | 1.97x faster |\n")
            if MEASURED.search(t)]
    assert rows and all(BACKING.search(t) for t in rows)          # a table row: its caption's study
    items = blocks(f"Plain.\n\n- one item, 5 ms a frame\n- another, {study}\n")
    assert MEASURED.search(items[1][1]) and not BACKING.search(items[1][1])   # a list item: its own


# --- studies ----------------------------------------------------------------------------------------

STUDY_PAGES = sorted(p for p in STUDIES.glob("*.md") if p.name != "README.md")
INDEX = (STUDIES / "README.md").read_text()
HASH = re.compile(r"\bcommits?\b[^.\n]{0,80}?\b([0-9a-f]{7,40})\b")


def _git_knows() -> bool:
    try:
        out = subprocess.run(["git", "rev-parse", "--is-shallow-repository"], cwd=REPO, capture_output=True,
                             text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return False
    return out == "false"


@pytest.mark.parametrize("page", STUDY_PAGES, ids=lambda p: p.name)
def test_every_study_names_the_commit_it_measured(page):
    text = " ".join(page.read_text().split())
    hashes = HASH.findall(text)
    assert hashes, f"{page.name} names no commit (a **Commit.** paragraph: \"measured with the code of commit X\")"
    if _git_knows():
        for h in hashes:
            ok = subprocess.run(["git", "cat-file", "-e", f"{h}^{{commit}}"], cwd=REPO, capture_output=True)
            assert ok.returncode == 0, f"{page.name}: commit {h} is not in this repository's history"


def index_rows() -> dict[str, str]:
    """The studies index's rows by the page they link first."""
    rows = {}
    for line in INDEX.splitlines():
        m = re.match(r"\| \[[^\]]+\]\(([\w.-]+\.md)\) \|", line)
        if m:
            rows[m.group(1)] = line
    return rows


def test_every_study_is_in_the_index_as_current_or_superseded():
    rows = index_rows()
    names = {p.name for p in STUDY_PAGES}
    assert names == set(rows), (f"docs/studies/README.md lacks {sorted(names - set(rows))}, "
                                f"lists missing pages {sorted(set(rows) - names)}")
    for name, row in rows.items():
        status = row.rstrip(" |").rsplit(" | ", 1)[-1]
        assert status.startswith(("current", "superseded by [")), f"{name}: status {status!r}"
        if status.startswith("superseded"):
            by = re.findall(r"\]\(([\w.-]+\.md)\)", status)
            assert by and all(b in names and b != name for b in by), f"{name}: superseded by {by}"
        assert re.search(r"\| [0-9a-f]{7}", row), f"{name}: the index names no commit"


def test_the_citation_rule_reads_code_as_its_readers_do(tmp_path):
    """Adjacent string literals and wrapped docstrings are read whole; a section must exist."""
    src = tmp_path / "m.py"
    src.write_text('"""The pointer (docs/training.md "What the objects\n    add")."""\n'
                   'HELP = ("see docs/pipeline.md, "\n        "\\"Head position\\"")  # docs/store.md#layout\n')
    found = [m.groups() for m in CITE.finditer(python_text(src))]
    assert found == [("docs/training.md", None, "What the objects add", None),
                     ("docs/pipeline.md", None, "Head position", None),
                     ("docs/store.md", "layout", None, None)]
    training, pipeline = (DOCS / "training.md").read_text(), (DOCS / "pipeline.md").read_text()
    assert not has_section(training, "What the objects add")             # a study page now
    assert has_section(training, "The output") and has_section(pipeline, "Head position")
    assert has_section(pipeline, "Object positions")                     # a bold paragraph label
    assert not has_section(pipeline, "Head")                             # a prefix of a word is not a section
    assert slug("Data-parallel training (torchrun, ga3ce_prep/train/distributed.py)") == \
        "data-parallel-training-torchrun-ga3ce_preptraindistributedpy"
    assert slug("GFIE's gaze-following modules: `eval --gfm` (ga3ce_prep/train/gfm.py)") == \
        "gfies-gaze-following-modules-eval---gfm-ga3ce_preptraingfmpy"
