"""Each default declared once (issue 39): the plan rate, the plan horizon and the planner's time
gap are each defined by one named constant in ``safeil_sumo/core/policy.py``, and no other module of
the package writes the literal value as a default of a parameter, field, option or key of that
name; they refer to the constant instead, so changing it changes every command, environment
and planner at once.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "safeil_sumo"
HOME = "core/policy.py"
# constant: (its value, the names whose default it is: parameters, fields, options, keys)
DEFAULTS: dict[str, tuple[float, frozenset[str]]] = {
    "PLAN_RATE_HZ": (10.0, frozenset({"plan_rate_hz", "plan_rate"})),
    "PLAN_HORIZON_S": (5.0, frozenset({"horizon", "horizon_s"})),
    "DEFAULT_TIME_GAP_S": (1.5, frozenset({"time_gap_s", "time_gap"})),
}
# literal defaults left, each with its reason (remove an entry once it refers to the constant)
ALLOWED: dict[tuple[str, str], str] = {
    ("planners/idm.py", "horizon"): "idm.py is being edited on another branch; PLAN_HORIZON_S once merged",
    ("planners/idm.py", "horizon_s"): "idm.py is being edited on another branch (its JSON's horizon_s)",
    ("planners/idm.py", "time_gap_s"): "idm.py is being edited on another branch; the IDM's T parameter",
}


def _is_literal(node: ast.AST | None, value: float) -> bool:
    return (isinstance(node, ast.Constant) and not isinstance(node.value, bool)
            and isinstance(node.value, int | float) and node.value == value)


def _key(node: ast.AST | None) -> str | None:
    """A name given as a string: ``"horizon_s"``, or an option ``"--plan-rate-hz"``."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return node.value.lstrip("-").replace("-", "_")
    return None


def literal_defaults(source: str, names: frozenset[str], value: float) -> list[tuple[int, str]]:
    """``(line, name)`` of every place in ``source`` that writes ``value`` as the default of one
    of ``names``: a parameter's default, a class field (``x: float = v`` or ``field(default=v)``),
    a keyword argument (``f(name=v)``), an option (``add_argument("--name", default=v)``), a
    dict entry (``{"name": v}``) or a lookup (``d.get("name", v)``)."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda):
            a = node.args
            positional = [*a.posonlyargs, *a.args]
            pairs = list(zip(positional[len(positional) - len(a.defaults):], a.defaults,
                             strict=True))
            pairs += [(arg, d) for arg, d in zip(a.kwonlyargs, a.kw_defaults, strict=True) if d]
            found += [(d.lineno, arg.arg) for arg, d in pairs
                      if arg.arg in names and _is_literal(d, value)]
        elif isinstance(node, ast.ClassDef):
            for stmt in node.body:
                target = stmt.target if isinstance(stmt, ast.AnnAssign) else (
                    stmt.targets[0] if isinstance(stmt, ast.Assign) else None)
                if not (isinstance(target, ast.Name) and target.id in names):
                    continue
                v = stmt.value
                if isinstance(v, ast.Call):  # dataclasses.field(default=...)
                    v = next((k.value for k in v.keywords if k.arg == "default"), None)
                if _is_literal(v, value):
                    found.append((stmt.lineno, target.id))
        elif isinstance(node, ast.Call):
            found += [(k.value.lineno, k.arg) for k in node.keywords
                      if k.arg in names and _is_literal(k.value, value)]
            first = _key(node.args[0]) if node.args else None
            if first in names:
                default = next((k.value for k in node.keywords if k.arg == "default"), None)
                is_get = isinstance(node.func, ast.Attribute) and node.func.attr == "get"
                if is_get and len(node.args) > 1:
                    default = node.args[1]
                if _is_literal(default, value):
                    found.append((node.lineno, first))
        elif isinstance(node, ast.Dict):
            found += [(v.lineno, k) for key, v in zip(node.keys, node.values, strict=True)
                      if (k := _key(key)) in names and _is_literal(v, value)]
    return sorted(found)


def definitions(source: str, constant: str) -> list[ast.AST]:
    """The module-level assignments of ``constant`` in ``source``: their values."""
    out = []
    for node in ast.parse(source).body:
        if isinstance(node, ast.Assign):
            if any(isinstance(t, ast.Name) and t.id == constant for t in node.targets):
                out.append(node.value)
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and (
                node.target.id == constant):
            out.append(node.value)
    return out


def sources() -> dict[str, str]:
    return {p.relative_to(PKG).as_posix(): p.read_text() for p in sorted(PKG.rglob("*.py"))}


def test_the_finder_by_hand() -> None:
    src = '''
from dataclasses import dataclass, field
def f(a, horizon=5.0, *, plan_rate_hz=10.0, other=5.0): ...
def g(horizon=PLAN_HORIZON_S, horizon_s=5): ...
@dataclass
class C:
    horizon: float = 5.0
    time_gap_s: float = field(default=1.5)
    lateral_tau_s: float = 1.5
run(horizon_s=5.0, step_s=5.0)
p.add_argument("--plan-rate-hz", type=float, default=10.0)
p.add_argument("--rate-hz", type=float, default=10.0)
doc = {"horizon_s": 5.0, "far": 5.0}
h = doc.get("horizon_s", 5.0)
t = doc.get("time_gap_s", 2.0)
'''
    horizon = frozenset({"horizon", "horizon_s"})
    assert literal_defaults(src, horizon, 5.0) == [
        (3, "horizon"), (4, "horizon_s"), (7, "horizon"), (10, "horizon_s"), (13, "horizon_s"),
        (14, "horizon_s")]
    assert literal_defaults(src, frozenset({"plan_rate_hz"}), 10.0) == [
        (3, "plan_rate_hz"), (11, "plan_rate_hz")]
    assert literal_defaults(src, frozenset({"time_gap_s"}), 1.5) == [(8, "time_gap_s")]
    assert definitions("A = 1.0\nB: float = 2.0\ndef f():\n    A = 3.0\n", "A")[0].value == 1.0
    assert definitions("B: float = 2.0\n", "B")[0].value == 2.0


@pytest.mark.parametrize("constant", DEFAULTS)
def test_each_default_is_defined_in_one_place(constant: str) -> None:
    value, _ = DEFAULTS[constant]
    where = {rel: defs for rel, src in sources().items() if (defs := definitions(src, constant))}
    assert list(where) == [HOME], f"{constant} is defined in {sorted(where)}, not only {HOME}"
    (node,) = where[HOME]
    assert _is_literal(node, value), f"{HOME}: {constant} is no longer the literal {value:g}"


@pytest.mark.parametrize("constant", DEFAULTS)
def test_no_module_repeats_the_default_as_a_literal(constant: str) -> None:
    value, names = DEFAULTS[constant]
    repeated = [f"{rel}:{line}: {name} = {value} (use {constant} from safeil_sumo.core.policy)"
                for rel, src in sources().items()
                for line, name in literal_defaults(src, names, value)
                if (rel, name) not in ALLOWED]
    assert repeated == [], "\n".join(repeated)


def test_the_defaults_reach_every_consumer() -> None:
    """What users see: the loop, a scenario, the planners, the Gymnasium environments and the
    command lines all default to the constants."""
    import inspect

    from safeil_sumo.core import policy
    from safeil_sumo.envs.base import loop_config
    from safeil_sumo.envs.single import SafeILEnv
    from safeil_sumo.envs.vector import SafeILVectorEnv
    from safeil_sumo.planners.analytic import AnalyticPlanner
    from safeil_sumo.run import build_parser
    from safeil_sumo.scenarios.spec import Task
    from safeil_sumo.sim.loop_types import LoopConfig

    assert LoopConfig().plan_rate_hz == Task().loop.plan_rate_hz == policy.PLAN_RATE_HZ
    assert loop_config().plan_rate_hz == policy.PLAN_RATE_HZ
    assert build_parser().parse_args([]).plan_rate_hz == policy.PLAN_RATE_HZ
    for env in (SafeILEnv, SafeILVectorEnv):
        params = inspect.signature(env).parameters
        assert params["plan_rate_hz"].default == policy.PLAN_RATE_HZ
        assert params["horizon_s"].default == policy.PLAN_HORIZON_S
    assert AnalyticPlanner().horizon == policy.PLAN_HORIZON_S
    assert AnalyticPlanner().time_gap_s == policy.DEFAULT_TIME_GAP_S
