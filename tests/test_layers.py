"""The layers import downwards only: rafd (the library) imports none of export, service or tools; export imports rafd;
service imports rafd (never export: the image has no torch); tools may import everything. Every import statement is
read (module level and inside functions: a lazy import is still a dependency), so no package cycle can form. Every
package folder has an __init__.py."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
ALLOWED = {
    "rafd": set(),
    "export": {"rafd"},
    "service": {"rafd"},
    "tools": {"rafd", "export", "service"},
}


def imported_top_levels(path: Path) -> set[str]:
    """The first component of every module a file imports (absolute imports; relative ones stay in the package)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return names


@pytest.mark.parametrize("package", sorted(ALLOWED))
def test_a_package_imports_only_the_layers_below_it(package: str):
    offending = []
    for path in sorted((REPO / package).rglob("*.py")):
        for name in sorted(imported_top_levels(path) & (set(ALLOWED) - {package})):
            if name not in ALLOWED[package]:
                offending.append(f"{path.relative_to(REPO)} imports {name}")
    assert not offending, "\n".join(offending)


@pytest.mark.parametrize("package", ["rafd", "export", "service", "tools", "tests"])
def test_every_package_folder_has_an_init(package: str):
    folders = {p.parent for p in (REPO / package).rglob("*.py") if "__pycache__" not in p.parts}
    missing = [str(f.relative_to(REPO)) for f in sorted(folders) if not (f / "__init__.py").is_file()]
    assert not missing, missing
