"""The layers import downwards only: rafd (the library) imports none of export, service, bench or tools; export imports
rafd; service imports rafd (never export: the image has no torch); bench (every benchmark: it measures rafd, export
and service, so it sits above all three) imports those three; tools may import everything. Every import statement is
read (module level and inside functions: a lazy import is still a dependency), so no package cycle can form. Every
package folder has an __init__.py.

Inside rafd the sub-packages import downwards too, in the order of RAFD_LAYERS: the top-level modules (geometry,
config, preprocessing, the wire protocol) and the scan formats (rafd.scans), numpy and opencv only, at the bottom as
one layer, then the tracker (rafd.tracking: numpy + scipy, torch-free, for the service and evaluation alike), data,
the simulator, the model, the ONNX runtime, pictures, evaluation, training and the command line. So training may
call evaluation (validation during training) but evaluation never imports training: what both need (collation,
precision, the device) lives below both. And no module imports a private (underscore) name from another package."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
ALLOWED = {
    "rafd": set(),
    "export": {"rafd"},
    "service": {"rafd"},
    "bench": {"rafd", "export", "service"},
    "tools": {"rafd", "export", "service", "bench"},
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


# Lowest first; "core" is rafd's top-level modules and the packages of CORE_PACKAGES. A sub-package may import those
# before it, never one after it.
RAFD_LAYERS = ("core", "tracking", "assets", "data", "sim", "model", "runtime", "viz", "eval", "train", "cli")


def rafd_imports(path: Path) -> list[tuple[str, str]]:
    """(rafd unit imported, the name imported from it or "") for every rafd import in a file."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            found += [(alias.name, "") for alias in node.names if alias.name.startswith("rafd.")]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module and node.module.startswith("rafd."):
            found += [(node.module, alias.name) for alias in node.names]
    return found


# rafd.scans (the scan formats: Cartesian, RADIATE polar, Oxford / Boreas native) is part of core: numpy + opencv like
# the top-level modules, built on rafd.geometry, and rafd.preprocess's one path to the model input starts with its
# polar conversion, so neither can sit above the other.
CORE_PACKAGES = ("scans",)


def rafd_unit(module: str) -> str:
    """rafd.data.reader -> data; rafd.geometry, rafd.scans.polar -> core."""
    second = module.split(".")[1]
    return second if (REPO / "rafd" / second).is_dir() and second not in CORE_PACKAGES else "core"


def test_rafd_sub_packages_import_only_the_layers_below_them():
    offending = []
    for path in sorted((REPO / "rafd").rglob("*.py")):
        unit = rafd_unit(".".join(path.relative_to(REPO).with_suffix("").parts))
        assert unit in RAFD_LAYERS, f"rafd/{unit} is in no layer of RAFD_LAYERS: place it"
        for module, _ in rafd_imports(path):
            target = rafd_unit(module)
            if RAFD_LAYERS.index(target) > RAFD_LAYERS.index(unit):
                offending.append(f"{path.relative_to(REPO)} ({unit}) imports {module} ({target}, a layer above)")
    assert not offending, "\n".join(offending)


@pytest.mark.parametrize("package", sorted(ALLOWED))
def test_no_private_name_is_imported_across_packages(package: str):
    offending = []
    for path in sorted((REPO / package).rglob("*.py")):
        here = ".".join(path.relative_to(REPO).parts[:-1])
        for module, name in rafd_imports(path):
            if name.startswith("_") and not name.startswith("__") and module.rsplit(".", 1)[0] != here:
                offending.append(f"{path.relative_to(REPO)} imports the private {module}.{name}")
    assert not offending, "\n".join(offending)


@pytest.mark.parametrize("package", ["rafd", "export", "service", "tools", "tests"])
def test_every_package_folder_has_an_init(package: str):
    folders = {p.parent for p in (REPO / package).rglob("*.py") if "__pycache__" not in p.parts}
    missing = [str(f.relative_to(REPO)) for f in sorted(folders) if not (f / "__init__.py").is_file()]
    assert not missing, missing
