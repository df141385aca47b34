"""The mutation-testing habit (docs/mutation_testing.md): every safety-critical module's code is
the code its last mutation run measured. A change to one of these modules fails here until its
mutants are run again and recorded (`python tools/mutation.py run "<module>.*"`, then
`record`), and a record below the 90 % target, or with mutants of its sample not run, does not
land. The kill rates themselves are reported in docs/mutation_testing.md."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _tool():
    spec = importlib.util.spec_from_file_location("mutation_tool", ROOT / "tools" / "mutation.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


TOOL = _tool()


@pytest.mark.parametrize("module", TOOL.SAFETY_MODULES)
def test_the_safety_module_is_the_code_its_mutation_run_measured(module: str) -> None:
    record = json.loads(TOOL.RECORD.read_text())["modules"]
    path = str(TOOL.module_path(module))
    assert path in record, f"{path}: no mutation run recorded"
    assert TOOL.source_digest(ROOT / path) == record[path]["source_digest"], (
        f"{path} changed since its mutation run: python tools/mutation.py run '{module}.*' "
        "(then judge the survivors) and python tools/mutation.py record")
    entry = record[path]
    assert entry["not run"] == 0, f"{path}: {entry['not run']} mutants of its sample not run"
    assert entry["kill_rate"] >= 0.9, f"{path}: kill rate {entry['kill_rate']} below 90 %"


def test_the_digest_ignores_documentation_and_sees_code(tmp_path: Path) -> None:
    base = 'def f(x):\n    """Doc."""\n    return x + 1  # one\n'
    same = '# a comment\n\ndef f(x):\n    """Other doc,\n    two lines."""\n\n    return x + 1\n'
    code = 'def f(x):\n    """Doc."""\n    return x - 1  # one\n'
    text = 'def f(x):\n    """Doc."""\n    return "x + 1"\n'
    digests = []
    for k, src in enumerate((base, same, code, text)):
        (tmp_path / f"m{k}.py").write_text(src)
        digests.append(TOOL.source_digest(tmp_path / f"m{k}.py"))
    assert digests[0] == digests[1]
    assert len({digests[0], digests[2], digests[3]}) == 3
