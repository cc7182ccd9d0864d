"""Figures quoted in the docs are still in the committed tables they cite.

A paragraph or bullet of ``docs/findings.md`` (or ``tables/README.md``) that quotes a decimal
figure names the table it comes from (``tables/table1_self.md``...); every such figure must
appear, as a whole number token, in one of the tables its paragraph cites. When the tables are
re-made from new records and a figure changes, this fails and names the figure, so the prose
is updated with the tables instead of drifting from them.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
CHECKED = [ROOT / "docs" / "findings.md", ROOT / "tables" / "README.md"]
TABLE_REF = re.compile(r"tables/[\w./-]+?\.md")
DECIMAL = re.compile(r"(?<![\w.])\d+\.\d+(?![\w.]*\d)")


def paragraphs(text: str) -> list[str]:
    """Blank-line separated blocks, each bullet ("- ...", with its continuation lines) its own."""
    out: list[str] = []
    for block in re.split(r"\n\s*\n", text):
        if block.lstrip().startswith("```"):
            continue
        current: list[str] = []
        for line in block.splitlines():
            if re.match(r"\s*[-*] ", line) and current:
                out.append("\n".join(current))
                current = []
            current.append(line)
        if current:
            out.append("\n".join(current))
    return out


def figures(paragraph: str) -> list[str]:
    # inline code (config keys such as `guidance.select_fraction = 0.2`) and links are not figures
    prose = re.sub(r"`[^`]*`|\]\([^)]*\)", " ", paragraph)
    return DECIMAL.findall(prose)


def check(doc: Path) -> list[str]:
    problems = []
    for par in paragraphs(doc.read_text()):
        found = figures(par)
        if not found:
            continue
        cited = sorted(set(TABLE_REF.findall(par)))
        if not cited:
            problems.append(f"{doc.name}: figures {found} quoted without naming the table they come from: {par[:80]!r}")
            continue
        texts = []
        for ref in cited:
            path = ROOT / ref
            if not path.exists():
                problems.append(f"{doc.name}: cites {ref}, which does not exist")
                continue
            texts.append(path.read_text())
        for fig in found:
            pat = re.compile(r"(?<![\w.])" + re.escape(fig) + r"(?![\w]|\.\d)")
            if not any(pat.search(t) for t in texts):
                problems.append(f"{doc.name}: {fig} is not in {', '.join(cited)}: {par[:80]!r}")
    return problems


def test_parsing_on_a_small_example(tmp_path):
    table = tmp_path / "tables" / "t.md"
    table.parent.mkdir()
    table.write_text("| lmgs | 0.0049 ± 0.0007 | 36.69 |\n")
    assert figures("LPIPS 0.0049 ± 0.0007, `x = 0.5`, [a](b.md), 2026-11-25, 20 %") == ["0.0049", "0.0007"]
    assert len(paragraphs("a 1.0\n\n- b 2.0\n  c\n- d 3.0\n```\n4.0\n```")) == 3


@pytest.mark.parametrize("doc", CHECKED, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_quoted_figures_are_in_the_cited_tables(doc):
    assert check(doc) == []


def test_a_changed_figure_is_caught(tmp_path, monkeypatch):
    """The check fails when a quoted figure is no longer in the table (it is not vacuous)."""
    doc = ROOT / "docs" / "findings.md"
    text = doc.read_text()
    assert "0.0060 ± 0.0008" in text
    changed = tmp_path / "findings.md"
    changed.write_text(text.replace("0.0060 ± 0.0008", "0.0061 ± 0.0008", 1))
    problems = check(changed)
    assert len(problems) == 1 and "0.0061" in problems[0]
