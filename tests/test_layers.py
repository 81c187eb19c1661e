"""Import layers: splatcli's top-level packages and modules import only down the table in
docs/architecture.md ("Import layers"), and never in a cycle.

Every module under splatcli/ is parsed with `ast` (nothing is imported, so this takes well
under a second). Each import is mapped to the top-level package or module of splatcli it
lands in: `cli/`, `model.py`, or `__init__.py` for the package itself (`from splatcli import
__version__`). An import within one top-level package is that package's own business and
is not checked.

What counts: every `import` and `from ... import` statement, at module level or inside a
function (a lazy import still runs, so it still ties the two layers together). What does
not: imports under `if TYPE_CHECKING:` (they never run; a type named from above is the one
thing they are for), and imports by a string (`importlib`, `resources.files`), which
nothing here does across packages. There are no known exceptions: an upward import or a
cycle is fixed in the code, or the table is changed in the doc, never listed here.

Two checks, each failing with the module, line and import that break it:
1. no import cycle between top-level packages and modules (the graph alone, the table aside);
2. no upward import: a row of the table imports only from the rows below it, never its own
   row or one above; every top-level package and module is in the table exactly once.
"""

from __future__ import annotations

import ast
import re
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "splatcli"
DOC = ROOT / "docs" / "architecture.md"
HEADING = "## Import layers"


@dataclass(frozen=True)
class Edge:
    source: str  # the importing module's file, relative to the repository
    line: int
    target: str  # the dotted name imported
    frm: str  # the top-level node of each end
    to: str

    def __str__(self) -> str:
        return f"{self.source}:{self.line} imports {self.target}"


def node_of(dotted: str) -> str:
    """The top-level node a `splatcli...` name lands in: 'cli/', 'model.py' or '__init__.py'."""
    parts = dotted.split(".")[1:]
    if not parts:
        return "__init__.py"
    return f"{parts[0]}/" if (PACKAGE / parts[0]).is_dir() else f"{parts[0]}.py"


def is_module(dotted: str) -> bool:
    path = ROOT.joinpath(*dotted.split("."))
    return path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()


def type_checking_only(tree: ast.Module) -> set[int]:
    """ids of the nodes under `if TYPE_CHECKING:` (or `typing.TYPE_CHECKING`)."""
    skipped: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and ast.unparse(node.test) in ("TYPE_CHECKING", "typing.TYPE_CHECKING"):
            for child in node.body:
                skipped.update(id(n) for n in ast.walk(child))
    return skipped


def module_edges(path: Path) -> list[Edge]:
    rel = path.relative_to(ROOT)
    parts = rel.with_suffix("").parts
    dotted = ".".join(parts[:-1] if path.name == "__init__.py" else parts)  # splatcli.render, splatcli.render.sh
    package = dotted if path.name == "__init__.py" else dotted.rpartition(".")[0]
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(rel))
    skipped = type_checking_only(tree)
    edges = []
    for node in ast.walk(tree):
        if id(node) in skipped:
            continue
        targets: list[str] = []
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base_parts = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join(base_parts + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            # `from . import render` lands in render/; `from .. import __version__` in the package
            targets = [f"{base}.{a.name}" if is_module(f"{base}.{a.name}") else base for a in node.names]
        for target in targets:
            if target != "splatcli" and not target.startswith("splatcli."):
                continue
            frm, to = node_of(dotted), node_of(target)
            if frm != to:
                edges.append(Edge(str(rel), node.lineno, target, frm, to))
    return edges


def all_edges() -> list[Edge]:
    return [e for path in sorted(PACKAGE.rglob("*.py")) for e in module_edges(path)]


def top_level_nodes() -> set[str]:
    nodes = {f"{p.name}/" for p in PACKAGE.iterdir() if (p / "__init__.py").is_file()}
    return nodes | {p.name for p in PACKAGE.glob("*.py")}


def layers_from_doc() -> list[list[str]]:
    """The rows of the doc's table, top first: the packages (`x/`) and modules (`x.py`) named
    in backticks in each row's second column."""
    text = DOC.read_text(encoding="utf-8")
    assert HEADING in text, f"{DOC.relative_to(ROOT)} has no '{HEADING}' section"
    section = text.split(HEADING, 1)[1].split("\n## ", 1)[0]
    rows = []
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if not line.startswith("|") or len(cells) < 2 or set(cells[1]) <= set("-: "):
            continue
        names = re.findall(r"`([\w.]+/|[\w.]+\.py)`", cells[1])
        if names:
            rows.append(names)
    return rows


def find_cycle(edges: list[Edge]) -> list[Edge] | None:
    """One cycle in the node graph as the edges that close it, or None."""
    out: dict[str, dict[str, Edge]] = defaultdict(dict)
    for e in edges:
        out[e.frm].setdefault(e.to, e)
    state: dict[str, int] = {}  # 1 on the stack, 2 done
    stack: list[Edge] = []

    def visit(node: str) -> list[Edge] | None:
        state[node] = 1
        for to, edge in sorted(out[node].items()):
            if state.get(to) == 1:
                start = next(i for i, e in enumerate(stack) if e.frm == to) if to != node else len(stack)
                return stack[start:] + [edge]
            if to not in state:
                stack.append(edge)
                found = visit(to)
                if found:
                    return found
                stack.pop()
        state[node] = 2
        return None

    for node in sorted(out):
        if node not in state:
            found = visit(node)
            if found:
                return found
    return None


def test_no_import_cycle_between_top_level_packages():
    cycle = find_cycle(all_edges())
    if cycle:
        names = " -> ".join([cycle[0].frm] + [e.to for e in cycle])
        pytest.fail(f"import cycle: {names}\n" + "\n".join(f"  {e}" for e in cycle), pytrace=False)


def test_imports_only_go_down_the_layers():
    rows = layers_from_doc()
    row_of: dict[str, int] = {}
    for i, names in enumerate(rows):
        for name in names:
            assert name not in row_of, f"{name} is in two rows of the table in {DOC.relative_to(ROOT)}"
            row_of[name] = i
    nodes = top_level_nodes()
    missing = sorted(nodes - set(row_of))
    assert not missing, f"not in the '{HEADING}' table of {DOC.relative_to(ROOT)}: {missing}; add each to its row"
    stale = sorted(set(row_of) - nodes)
    assert not stale, f"in the '{HEADING}' table of {DOC.relative_to(ROOT)} but not in splatcli/: {stale}"
    # rows are listed top first: a row may import only from rows after it
    upward = [
        f"  {e} ({e.to}, {'the same row as' if row_of[e.to] == row_of[e.frm] else 'a row above'} {e.frm})"
        for e in all_edges()
        if row_of[e.to] <= row_of[e.frm]
    ]
    if upward:
        pytest.fail(f"imports that do not go down the table in {DOC.relative_to(ROOT)}:\n" + "\n".join(upward), pytrace=False)


def test_the_checker_sees_imports():
    """The checks above pass vacuously if nothing is found: known edges, including a lazy one
    and one to the package itself, must be."""
    found = {(e.frm, e.to) for e in all_edges()}
    assert {("train/", "eval/"), ("cli/", "train/"), ("formats/", "files/"), ("project.py", "__init__.py")} <= found
    assert ("__init__.py", "render/") in found  # splatcli.__getattr__'s lazy `from . import render`
    assert find_cycle([Edge("a.py", 1, "splatcli.b", "a.py", "b/"), Edge("b/x.py", 2, "splatcli.a", "b/", "a.py")])
    assert len(layers_from_doc()) >= 5


def imported_names(path: Path) -> list[tuple[int, str]]:
    """(line, dotted name) of every absolute import in a file."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
            found.append((node.lineno, node.module))
    return found


def test_bench_and_tests_keep_to_their_own():
    """splatcli/ imports neither bench/ nor tests/; bench/ uses the package and its own helpers,
    never tests/ (its support is for tests); tests/ never import a benchmark (test_bench runs them
    as children)."""
    own_bench = {p.stem for p in (ROOT / "bench").glob("*.py")}
    rules = [(PACKAGE, ("bench", "tests") + tuple(own_bench)), (ROOT / "bench", ("tests", "support")),
             (ROOT / "tests", ("bench",) + tuple(own_bench - {"conftest"}))]
    wrong = [f"  {path.relative_to(ROOT)}:{line} imports {name}"
             for folder, banned in rules for path in sorted(folder.rglob("*.py"))
             for line, name in imported_names(path) if name.split(".")[0] in banned]
    if wrong:
        pytest.fail("imports across splatcli/, bench/ and tests/:\n" + "\n".join(wrong), pytrace=False)


# The rasterizer's hand-written kernels and its reference twin read best whole, as the math they follow.
LONG_ALLOWED = {("render/projection.py", "forward"), ("render/projection.py", "_backward"),
                ("render/reference.py", "rasterize_reference")}
MAX_FUNCTION_LINES = 60


def test_functions_are_short():
    long = []
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = str(path.relative_to(PACKAGE))
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and (rel, node.name) not in LONG_ALLOWED:
                lines = node.end_lineno - node.lineno + 1
                if lines > MAX_FUNCTION_LINES:
                    long.append(f"  splatcli/{rel}:{node.lineno} {node.name}: {lines} lines")
    if long:
        pytest.fail(f"functions over {MAX_FUNCTION_LINES} lines:\n" + "\n".join(long), pytrace=False)
