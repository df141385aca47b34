"""The test suite's own rules (tests/conftest.py): a test that starts SUMO is marked ``sumo``, and
no test file imports another (shared helpers live in conftest.py and tests/fixtures_*.py)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from safeil_sumo.sim import sumo_api

TESTS = Path(__file__).resolve().parent


def imported_test_files(source: str) -> set[str]:
    """The test files (``test_*`` modules, bare or as ``tests.test_*``) that ``source`` imports,
    anywhere in it."""
    found = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names
                                     if node.module == "tests"]
        else:
            continue
        found |= {n for n in names if n.removeprefix("tests.").startswith("test_")}
    return found


def test_the_import_finder_by_hand() -> None:
    src = ("import test_a\nfrom test_b import x\nfrom tests.test_c import y\nfrom tests import "
           "test_d\nimport fixtures_data\nfrom tests.fixtures_data import z\nfrom testing import t\n"
           "def f():\n    from test_e import g\n")
    assert imported_test_files(src) == {"test_a", "test_b", "tests.test_c", "tests.test_d",
                                        "test_e"}


def test_no_test_file_imports_another() -> None:
    imports = {p.name: sorted(found) for p in sorted(TESTS.rglob("*.py"))
               if (found := imported_test_files(p.read_text()))}
    assert imports == {}, ("move what they share into tests/conftest.py or a tests/fixtures_*.py "
                           f"module: {imports}")


def test_an_unmarked_test_that_starts_sumo_fails() -> None:
    """This test is not marked ``sumo``: conftest's guard fails it at the start, before SUMO
    runs (it would be selected by ``-m "not sumo"``)."""
    with pytest.raises(pytest.fail.Exception, match="starts SUMO but is not marked sumo"):
        sumo_api.start(["-n", "no.net.xml"])
