"""The documentation holds to the code: commands answer --help, figures name a benchmark that
prints them, the configuration reference is generated, the README stays short."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from typer.testing import CliRunner

from cellsight.cli import app
from cellsight.config_docs import markdown

ROOT = Path(__file__).resolve().parents[2]
README = (ROOT / "README.md").read_text()
PERFORMANCE = (ROOT / "docs" / "performance.md").read_text()


def readme_commands() -> list[list[str]]:
    """The commands of the README's command table, as argument lists after ``cellsight``."""
    return [m.group(1).split() for m in re.finditer(r"^\| `cellsight ([a-z0-9 -]+)` \|", README, re.M)]


def performance_rows() -> list[tuple[str, str]]:
    """(figure key, benchmark module) of every figure row of docs/performance.md."""
    rows = []
    for line in PERFORMANCE.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        command = re.search(r"python -m benchmarks\.(\w+)", line)
        if line.startswith("|") and command and cells[0].startswith("`"):
            rows.append((cells[0].strip("`"), command.group(1)))
    return rows


def test_the_readme_lists_every_top_level_command() -> None:
    listed = {cmd[0] for cmd in readme_commands()}
    assert {c.name for c in app.registered_commands} | {g.name for g in app.registered_groups} <= listed


@pytest.mark.parametrize("command", readme_commands(), ids=" ".join)
def test_every_command_in_the_readme_answers_help(command: list[str]) -> None:
    result = CliRunner().invoke(app, [*command, "--help"])
    assert result.exit_code == 0, result.output
    assert "Usage" in result.output


def printed_keys(source: str) -> list[re.Pattern[str]]:
    """The figure names a benchmark's source can print: its string literals, f-strings with their
    replacement fields as wildcards (``f"adds_recall_{cls}"``)."""
    literals = re.findall(r'f?"([A-Za-z0-9_{}.\[\]]+)"', source)
    return [re.compile(re.sub(r"\\\{[^}]*\\\}", r"[a-z0-9_]*", re.escape(lit))) for lit in literals]


def test_every_figure_names_a_benchmark_that_prints_it() -> None:
    rows = performance_rows()
    assert len(rows) >= 10, "docs/performance.md lost its table"
    for key, module in rows:
        source = ROOT / "benchmarks" / f"{module}.py"
        assert source.is_file(), f"{key}: python -m benchmarks.{module} does not exist"
        assert any(p.fullmatch(key) for p in printed_keys(source.read_text())), f"{key}: benchmarks.{module} does not print it"


def test_the_configuration_reference_is_what_the_models_say() -> None:
    assert (ROOT / "docs" / "configuration.md").read_text() == markdown(), "run: cellsight config docs > docs/configuration.md"


def test_the_readme_is_short_and_states_the_suites_time() -> None:
    assert len(README.splitlines()) <= 250
    assert re.search(r'pytest -m "not slow".*\d+ s', README) and re.search(r"everything.*\d+ min", README)


def test_only_geometry_defines_a_rotation_angle() -> None:
    """The angle of a rotation (from its trace, or atan2 of its axis part) has one home."""
    pattern = re.compile(r"(arccos|acos|arctan2|atan2)\(.*trace|trace.*(arccos|acos)|def rotation_angle")
    offenders = []
    for package in ("schemas", "drivers", "estimator", "recognition", "cellsight", "benchmarks", "tests"):
        for f in (ROOT / package).rglob("*.py"):
            if f.name == "geometry.py" or f == Path(__file__).resolve():
                continue
            offenders += [f"{f.relative_to(ROOT)}:{i}" for i, line in enumerate(f.read_text().splitlines(), 1) if pattern.search(line)]
    assert not offenders, offenders


def test_no_document_repeats_a_paragraph() -> None:
    """A bad edit once inserted one paragraph between every character of design.md (400k lines):
    every document stays readable-sized, and no paragraph of four lines or more appears twice."""
    for doc in sorted((ROOT / "docs").glob("*.md")):
        text = doc.read_text()
        assert len(text.splitlines()) < 1500, f"{doc.name} has {len(text.splitlines())} lines"
        paragraphs = [p for p in text.split("\n\n") if p.count("\n") >= 3 and not p.startswith("|")]  # generated tables may repeat
        repeated = {p[:60] for p in paragraphs if paragraphs.count(p) > 1}
        assert not repeated, f"{doc.name} repeats {repeated}"
