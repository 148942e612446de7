"""The package boundaries of docs/architecture.md, checked on the source."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "segs"
FORBIDDEN = {
    "raster": ("segs.",),
    "data": ("segs.slam", "segs.modules", "segs.raster", "segs.callbacks", "segs.train"),
    "slam": ("segs.modules", "segs.raster", "segs.callbacks", "segs.train"),
    "modules": ("segs.slam", "segs.callbacks", "segs.train"),
}


def _imports(path: Path) -> list[str]:
    tree = ast.parse(path.read_text())
    names = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.append(node.module)
    return names


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_package_does_not_import_across_the_boundary(package):
    bad = []
    for path in (SRC / package).rglob("*.py"):
        for name in _imports(path):
            if name.startswith(FORBIDDEN[package]) and not (package == "raster" and name == "segs"):
                bad.append(f"{path.relative_to(SRC)} imports {name}")
    assert not bad, bad


def test_files_stay_reasonably_small():
    big = [f"{p.relative_to(SRC)}: {n}" for p in SRC.rglob("*.py") if (n := len(p.read_text().splitlines())) > 650]
    assert not big, big
