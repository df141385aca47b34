"""The front page keeps its promises (issue 39): every ```python block of the README runs as
written, and every relative link of README.md, CHANGELOG.md and docs/*.md points at a file that
exists (and, into a Markdown file, at a heading it has)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
LINKED_DOCS = [README, REPO / "CHANGELOG.md", *sorted((REPO / "docs").glob("*.md"))]

FENCED = re.compile(r"^(`{3,})[^\n]*\n.*?^\1[ \t]*$", re.DOTALL | re.MULTILINE)
PYTHON_BLOCK = re.compile(r"^```python\n(.*?)^```[ \t]*$", re.DOTALL | re.MULTILINE)
INLINE_CODE = re.compile(r"`[^`\n]*`")
LINK = re.compile(r"!?\[[^\]\n]*\]\(([^)\s]+)\)")
HEADING = re.compile(r"^#{1,6}[ \t]+(.+?)[ \t]*#*[ \t]*$", re.MULTILINE)


def python_blocks() -> list[tuple[int, str]]:
    """(line of the block's opening fence, its code) for every ```python block of the README."""
    text = README.read_text()
    return [(text.count("\n", 0, m.start()) + 1, m.group(1)) for m in PYTHON_BLOCK.finditer(text)]


def api_example_line() -> int:
    """The line of the block the README marks as the Python API example."""
    text = README.read_text()
    marker = text.index("<!-- python-example -->")
    return text.count("\n", 0, text.index("```python", marker)) + 1


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation (backticks too) dropped, spaces to
    hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.lower()).replace(" ", "-")


def anchors(path: Path) -> set[str]:
    text = FENCED.sub("", path.read_text())
    return {slug(h) for h in HEADING.findall(text)}


def relative_links(path: Path) -> list[str]:
    """The link targets of a Markdown file that are paths in the repository (code and fenced
    blocks left out: they are not rendered as links)."""
    text = INLINE_CODE.sub("``", FENCED.sub("", path.read_text()))
    return [t for t in LINK.findall(text) if not re.match(r"[a-z][a-z0-9+.-]*:", t)]


def test_the_readme_has_python_blocks() -> None:
    lines = [line for line, _ in python_blocks()]
    assert len(lines) >= 2 and api_example_line() in lines


@pytest.mark.sumo
@pytest.mark.parametrize("line", [line for line, _ in python_blocks()],
                         ids=lambda line: f"README.md:{line}")
def test_a_readme_python_block_runs(line: int, capsys) -> None:
    """Each block runs in a fresh namespace, as a reader would paste it. The API example drives
    behind a recorded NGSIM leader: it needs the shared data (skip without, fail under CI)."""
    code = dict(python_blocks())[line]
    pytest.importorskip("libsumo")  # every block runs the closed loop
    if 'leader_profile="ngsim"' in code:
        from fixtures_data import NGSIM_PAIRS, require_file

        require_file(NGSIM_PAIRS)
    namespace: dict = {"__name__": f"readme_block_{line}"}
    exec(compile(code, f"README.md:{line}", "exec"), namespace)  # noqa: S102 - our own README
    if line == api_example_line():
        shipped, mine = namespace["shipped"], namespace["mine"]
        assert list(shipped.summary["scenario"]) == ["s0000", "s0001"]
        assert (shipped.summary["flag"] == "").all()
        assert mine.summary["policy"].iloc[0] == "cautious" and len(mine.log) > 100
        assert "gap" in capsys.readouterr().out


@pytest.mark.parametrize("doc", LINKED_DOCS, ids=lambda p: str(p.relative_to(REPO)))
def test_every_relative_link_points_at_a_file(doc: Path) -> None:
    broken = []
    for target in relative_links(doc):
        file_part, _, anchor = target.partition("#")
        path = (doc.parent / file_part).resolve() if file_part else doc
        if not path.exists():
            broken.append(f"{target}: no such file")
            continue
        if anchor and path.suffix == ".md" and anchor not in anchors(path):
            broken.append(f"{target}: no heading #{anchor}")
    assert not broken, f"{doc.relative_to(REPO)}: " + "; ".join(broken)


def test_the_link_checker_sees_a_broken_link(tmp_path) -> None:
    """The checker itself: a link to a missing file or heading is found, code is not a link."""
    (tmp_path / "there.md").write_text("# A heading: `with code`\n")
    doc = tmp_path / "doc.md"
    doc.write_text("[ok](there.md#a-heading-with-code) [gone](missing.md) `[no](code.md)`\n"
                   "```\n[no](fenced.md)\n```\n[web](https://example.org) [bad](there.md#nope)\n")
    assert relative_links(doc) == ["there.md#a-heading-with-code", "missing.md", "there.md#nope"]
    assert anchors(tmp_path / "there.md") == {"a-heading-with-code"}
