"""The import direction of docs/architecture.md section 2: schemas <- drivers, estimator, recognition <- cellsight."""

from __future__ import annotations

import ast
from pathlib import Path

from schemas.regen import stale_files

ROOT = Path(__file__).resolve().parents[2]
OURS = {"schemas", "drivers", "estimator", "recognition", "cellsight"}
ALLOWED = {
    "schemas": {"schemas"},
    "drivers": {"drivers", "schemas"},
    "estimator": {"estimator", "schemas"},
    "recognition": {"recognition", "schemas"},
    "cellsight": OURS,
}


def imported_packages(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), str(path))
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.add(node.module.split(".")[0])
    return found & OURS


def test_imports_point_one_way() -> None:
    violations = []
    for package, allowed in ALLOWED.items():
        files = list((ROOT / package).rglob("*.py"))
        assert files, f"package {package}/ is missing"
        for f in files:
            bad = imported_packages(f) - allowed
            if bad:
                violations.append(f"{f.relative_to(ROOT)} imports {sorted(bad)}")
    assert not violations, "imports against the layout rule:\n" + "\n".join(violations)


def test_layout_checker_catches_a_violation(tmp_path: Path) -> None:
    bad = tmp_path / "x.py"
    bad.write_text("from estimator.graph import Estimator\nimport drivers.markers\n")
    assert imported_packages(bad) == {"estimator", "drivers"}


def test_no_production_code_reads_ground_truth() -> None:
    """Sim ground truth (truth/ keys) is for tests and benchmarks only."""
    offenders = []
    for package in ("estimator", "recognition"):
        for f in (ROOT / package).rglob("*.py"):
            if "truth" in f.read_text():
                offenders.append(str(f.relative_to(ROOT)))
    assert not offenders, f"production code mentions ground truth: {offenders}"


def test_generated_code_matches_proto_sources() -> None:
    assert stale_files() == [], "run: python -m schemas.regen"
