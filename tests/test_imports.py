"""The package's import graph has no cycle: no module of ga3ce_prep imports, through others, a module
that imports it back. Read with `ast`, not by importing: every intra-package import counts, at module
level and inside functions alike (a function-level import is a cycle that waits for its first
call), and importing a submodule counts as importing its packages too (Python runs their
__init__.py first). `if TYPE_CHECKING:` blocks never run, but a loop through them is a loop of
concepts, so the package is also checked with them in.

estimators/ holds its families only (segment, pose, view, depth, runtime; estimators/__init__.py),
and a family imports no other family but runtime/, the layer they share."""
import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "ga3ce_prep"
ESTIMATORS = "ga3ce_prep.estimators"
FAMILIES = {"segment", "pose", "view", "depth", "runtime"}
SHARED = "runtime"


def modules() -> dict[str, Path]:
    """Dotted module name -> file, for every module of the package (a package by its __init__.py)."""
    out = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def _type_checking_blocks(tree: ast.AST) -> set[int]:
    """ids of the nodes inside `if TYPE_CHECKING:` (or `typing.TYPE_CHECKING`) bodies."""
    skip: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and ast.unparse(node.test) in {"TYPE_CHECKING", "typing.TYPE_CHECKING"}:
            skip.update(id(n) for stmt in node.body for n in ast.walk(stmt))
    return skip


def imported_names(name: str, path: Path, type_only: bool = False) -> set[str]:
    """The dotted names module `name` imports anywhere in its file (relative ones resolved), each
    as the most specific name `from X import y` can mean (X.y for a submodule y, else X);
    type_only: `if TYPE_CHECKING:` imports too."""
    tree = ast.parse(path.read_text(), str(path))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    skip = set() if type_only else _type_checking_blocks(tree)
    out: set[str] = set()
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[:len(package.split(".")) - node.level + 1]
                base = ".".join(anchor + ([node.module] if node.module else []))
            out.update(f"{base}.{a.name}" for a in node.names)
            out.add(base)
    return out


def import_graph(type_only: bool = False) -> dict[str, set[str]]:
    """module -> the package's modules it imports: each name cut back to the module that holds it,
    plus that module's packages, except the importer's own (they are already being imported)."""
    mods = modules()
    graph: dict[str, set[str]] = {m: set() for m in mods}
    for m, path in mods.items():
        for target in imported_names(m, path, type_only):
            if target.split(".")[0] != PACKAGE.name:
                continue
            while target not in mods:
                target = target.rpartition(".")[0]
            while target and target != m and not m.startswith(target + "."):
                graph[m].add(target)
                target = target.rpartition(".")[0]
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of the graph as [a, b, ..., a], or None (iterative depth-first search)."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    for root in sorted(graph):
        if root in state:
            continue
        path, stack = [root], [iter(sorted(graph[root]))]
        state[root] = 1
        while stack:
            nxt = next(stack[-1], None)
            if nxt is None:
                state[path.pop()] = 2
                stack.pop()
            elif state.get(nxt) == 1:
                return path[path.index(nxt):] + [nxt]
            elif nxt not in state:
                state[nxt] = 1
                path.append(nxt)
                stack.append(iter(sorted(graph[nxt])))
    return None


def test_package_has_no_import_cycle():
    cycle = find_cycle(import_graph())
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_package_has_no_import_cycle_even_type_only():
    """Not even through annotations: a type-only loop (model/ga3ce.py <-> methods.py once, the model
    folder <-> pipeline/config.py later) is two modules that each need the other's concepts."""
    cycle = find_cycle(import_graph(type_only=True))
    assert cycle is None, "import cycle (type-only imports included): " + " -> ".join(cycle)


def test_weights_import_nothing_above_them():
    """weights/ (registry, model folder) sits below the pipeline, which checks its files against it;
    only its command line (weights/cli.py) loads pipelines."""
    graph = import_graph(type_only=True)
    below = {"ga3ce_prep.errors", "ga3ce_prep.files"}
    up = [f"{m} -> {t}" for m, ts in graph.items()
          if m.startswith("ga3ce_prep.weights") and m != "ga3ce_prep.weights.cli"
          for t in ts if not t.startswith("ga3ce_prep.weights") and t not in below]
    assert not up


def test_estimators_holds_its_families_only():
    entries = {p.name for p in (PACKAGE / "estimators").iterdir() if p.name != "__pycache__"}
    assert entries == {"__init__.py", "cli.py", *FAMILIES}
    assert all((PACKAGE / "estimators" / f / "__init__.py").is_file() for f in FAMILIES)


def test_a_family_imports_only_itself_and_runtime():
    crossing = [f"{m} -> {t}" for m, targets in import_graph().items() if m.startswith(ESTIMATORS + ".")
                for t in targets if t.startswith(ESTIMATORS + ".")
                and t.split(".")[2] not in {m.split(".")[2], SHARED} and m.split(".")[2] in FAMILIES]
    assert not crossing


def test_graph_reads_function_level_imports_and_packages():
    graph = import_graph()
    # stages/view.py imports its estimators inside methods only
    assert any(t.startswith("ga3ce_prep.estimators.") for t in graph["ga3ce_prep.stages.view"])
    # importing ga3ce_prep.synthetic.truth runs ga3ce_prep/synthetic/__init__.py first
    assert {"ga3ce_prep.synthetic.truth", "ga3ce_prep.synthetic"} <= graph["ga3ce_prep.stages.truth"]
    # `from . import amg` names the submodule; a package's __init__ imports its submodules
    assert "ga3ce_prep.estimators.segment.amg" in graph["ga3ce_prep.estimators.segment.mobilesam"]
    assert "ga3ce_prep.pipeline.run" in graph["ga3ce_prep.pipeline"]


def test_find_cycle():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": set()}) is None
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"a"}}) == ["a", "a"]
