"""The package's structure, checked from its source (docs/architecture.md): no import cycle, every
import runs down the layers, no function grows past 80 lines.

Imports inside functions count as much as those at the top: a lazy import hides a cycle from
Python, not from a reader. A new module must be given its layer in ``LAYERS``.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "safeil_sumo"

# bottom to top; a module may import its own layer and those below. A name ending in ".*" is a
# package and everything in it, unless a module of it is named in another layer.
LAYERS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("core: pure maths and the planner contract", ("core.*",)),
    ("planners: the analytic and IDM planners and the safety filter, pure numpy",
     ("planners.*",)),
    ("roads: SUMO nets and the geometry read from them", ("roads.*",)),
    ("data, learning and the closed loop; the planner registry, which loads checkpoints",
     ("data.*", "learn.*", "sim.*", "planners.registry")),
    ("scenarios: specs built into the loop's Scenario", ("scenarios.*",)),
    ("experiments: sweeps, replays, probes, metrics, animations", ("experiments.*",)),
    ("Gymnasium environments", ("envs.*",)),
    ("the Python API", ("api",)),
    ("the report card: safeil-evaluate's sections over the engines", ("report.*",)),
    ("command lines", ("run", "sweep", "replay", "probe", "gap_probe", "results", "bench",
                       "animate", "certify", "falsify", "evaluate", "train", "cli_args",
                       "studies.*")),
)
CLI_LAYER = next(i for i, (what, _) in enumerate(LAYERS) if what == "command lines")
# upward imports allowed, each with its reason (none today: keep it so)
ALLOWED_UPWARD: dict[tuple[str, str], str] = {}
# functions over MAX_FUNCTION_LINES, with their length then: they may shrink, not grow, and no
# other may join them (none today: issue 39 split the last five; keep it so)
LONG_FUNCTIONS: dict[str, int] = {}
MAX_FUNCTION_LINES = 80


def modules() -> dict[str, Path]:
    """``"scenarios.road" -> path`` for every module of the package (packages by their name)."""
    out = {}
    for path in PKG.rglob("*.py"):
        parts = path.relative_to(PKG).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = path
    return out


def imports(path: Path, known: dict[str, Path]) -> set[str]:
    """The package's modules that ``path`` imports, anywhere in it (``from a import b`` names
    module ``a.b`` when that is a module, else ``a``)."""

    def resolve(dotted: str) -> str | None:
        name = dotted.removeprefix("safeil_sumo").lstrip(".")
        while name and name not in known:
            name = name.rpartition(".")[0]
        return name or None

    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names if a.name.split(".")[0] == "safeil_sumo"]
        elif isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "safeil_sumo":
            targets = [f"{node.module}.{a.name}" for a in node.names]
        else:
            continue
        found |= {m for t in targets if (m := resolve(t))}
    return found


def import_graph() -> dict[str, set[str]]:
    known = modules()
    return {name: imports(path, known) - {name} for name, path in known.items() if name}


def layer_of(module: str) -> int | None:
    """The index in ``LAYERS`` of ``module`` (an exact name wins over a package's ``.*``)."""
    for i, (_, names) in enumerate(LAYERS):
        if module in names:
            return i
    for i, (_, names) in enumerate(LAYERS):
        if any(n.endswith(".*") and module.startswith(n[:-1]) for n in names):
            return i
    return None


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_cycle_finder_by_hand() -> None:
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": {"e2"}, "e2": {"e"}, "f": set()}
    assert sorted(cycles(graph)) == [["a", "b", "c"], ["e", "e2"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_layers_by_hand() -> None:
    assert layer_of("core.geometry") == 0 and layer_of("planners.idm") == 1
    assert layer_of("roads.road") == 2 and layer_of("scenarios.spec") == 4
    assert layer_of("sim.runner") == layer_of("learn.model") == layer_of("planners.registry") == 3
    assert layer_of("experiments.sweep_executor") == 5 and layer_of("run") == CLI_LAYER
    assert layer_of("envs.vector") == 6 and len(LAYERS) - 1 == CLI_LAYER
    assert layer_of("somewhere_new") is None


def test_imports_are_resolved_to_modules(tmp_path: Path) -> None:
    src = tmp_path / "m.py"
    src.write_text("import os\nfrom safeil_sumo.scenarios import road, nothing\n"
                   "def f():\n    from safeil_sumo.sim.runner import Scenario\n"
                   "    import safeil_sumo.core.geometry as g\n")
    known = {"scenarios": PKG, "scenarios.road": PKG, "sim": PKG, "sim.runner": PKG,
             "core.geometry": PKG}
    assert imports(src, known) == {"scenarios.road", "scenarios", "sim.runner", "core.geometry"}


def test_no_import_cycle() -> None:
    assert cycles(import_graph()) == []


def test_every_module_has_a_layer() -> None:
    packages = {p.parent.relative_to(PKG).as_posix().replace("/", ".")
                for p in PKG.rglob("__init__.py")}
    missing = sorted(m for m in import_graph() if m not in packages and layer_of(m) is None)
    assert missing == [], f"give these modules a layer in LAYERS: {missing}"


def test_imports_run_down_the_layers() -> None:
    upward = []
    for module, targets in import_graph().items():
        here = layer_of(module)
        for target in targets:
            there = layer_of(target)
            if here is not None and there is not None and there > here \
                    and (module, target) not in ALLOWED_UPWARD:
                upward.append(f"{module} ({LAYERS[here][0]}) -> {target} ({LAYERS[there][0]})")
    assert upward == [], "imports that run up the layers:\n" + "\n".join(sorted(upward))


def test_no_module_file_name_is_used_twice() -> None:
    """A module's file name says which module it is: ``replay.py`` names one module, not a
    command line and a library module both (``__init__.py`` aside)."""
    by_name: dict[str, list[str]] = {}
    for path in PKG.rglob("*.py"):
        if path.name != "__init__.py":
            by_name.setdefault(path.name, []).append(path.relative_to(PKG).as_posix())
    twice = {name: sorted(paths) for name, paths in sorted(by_name.items()) if len(paths) > 1}
    assert twice == {}, f"rename one of each: {twice}"


@pytest.mark.parametrize("path", sorted(PKG.rglob("*.py")), ids=lambda p: str(p.relative_to(PKG)))
def test_no_function_grows_past_80_lines(path: Path) -> None:
    """Every function and method, nested ones too, from its ``def`` line (decorators not
    counted) to its last line: ``end_lineno - lineno + 1``."""
    rel = path.relative_to(PKG).as_posix()
    long = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            lines = node.end_lineno - node.lineno + 1
            limit = LONG_FUNCTIONS.get(f"{rel}::{node.name}", MAX_FUNCTION_LINES)
            if lines > limit:
                long.append(f"{rel}::{node.name} (line {node.lineno}) has {lines} lines "
                            f"(at most {limit})")
    assert long == [], "split these into named steps:\n" + "\n".join(long)


def test_the_top_level_is_what_a_user_runs() -> None:
    """Library code lives in the folders; the package's top level holds the command lines
    (``python -m safeil_sumo.<name>``), their shared vocabulary and the Python API."""
    top = {p.stem for p in PKG.glob("*.py")} - {"__init__"}
    assert top == {m for m in LAYERS[CLI_LAYER][1] if "." not in m} | {"api"}


def test_console_scripts_name_the_python_m_commands() -> None:
    """Each ``[project.scripts]`` entry is ``safeil-<module>`` -> ``safeil_sumo.<module>:main``,
    for every command-line module with a ``main``, and that main prints its help."""
    import importlib
    import tomllib

    scripts = tomllib.loads((PKG.parent / "pyproject.toml").read_text())["project"]["scripts"]
    clis = {m for m in LAYERS[CLI_LAYER][1] if m not in ("cli_args", "studies.*")}
    assert {v.split(":")[0].removeprefix("safeil_sumo.") for v in scripts.values()} == clis
    for name, target in scripts.items():
        module, func = target.split(":")
        assert name == "safeil-" + module.removeprefix("safeil_sumo.").replace("_", "-")
        with pytest.raises(SystemExit) as exit_:
            getattr(importlib.import_module(module), func)(["--help"])
        assert exit_.value.code == 0
