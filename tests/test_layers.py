"""The layers import downwards only: rafd (the library) imports none of export, service, bench or tools; export imports
rafd; service imports rafd (never export: the image has no torch); bench (every benchmark: it measures rafd, export
and service, so it sits above all three) imports those three; tools may import everything. Every import statement is
read (module level and inside functions: a lazy import is still a dependency), so no package cycle can form. Every
package folder has an __init__.py.

Inside rafd the sub-packages import downwards too, in the order of RAFD_LAYERS: the top-level modules (geometry,
config, preprocessing, the wire protocol) and the scan formats (rafd.scans), numpy and opencv only, at the bottom as
one layer, then the tracker (rafd.tracking: numpy + scipy, torch-free, for the service and evaluation alike), the radar
odometry (which the data readers and the service run), ROS 2 bags (rafd.ros: a bag is a source of scans the data
layer reads), data, the simulator, the model, the ONNX runtime, pictures, evaluation, training and the command line.
So training may call evaluation (validation during training) but evaluation never imports training: what both need
(collation, precision, the device) lives below both. And no module imports a private (underscore) name from another
package.

Below the packages, no module imports itself back through others: the module graph (every import statement, those
inside functions and under TYPE_CHECKING too) has no cycle; an import inside a function is never a way around one."""

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
RAFD_LAYERS = (
    "core",
    "tracking",
    "assets",
    "odometry",
    "ros",
    "data",
    "sim",
    "model",
    "runtime",
    "viz",
    "eval",
    "train",
    "cli",
)


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


# ----------------------------------------------------------------------------- module cycles
SOURCE_PACKAGES = ("rafd", "export", "service", "bench", "tools")


def module_name(path: Path) -> str:
    """rafd/data/reader.py -> rafd.data.reader; rafd/data/__init__.py -> rafd.data."""
    parts = path.relative_to(REPO).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def module_graph() -> dict[str, set[str]]:
    """Module -> the project's modules it imports: `import a.b` and `from a import b` name module a.b where it exists,
    else `from a.b import name` names a.b; relative imports resolved against the importing module's package."""
    paths = {module_name(p): p for package in SOURCE_PACKAGES for p in (REPO / package).rglob("*.py")}
    graph: dict[str, set[str]] = {}
    for name, path in paths.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        edges: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                edges.update(alias.name for alias in node.names if alias.name in paths)
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    anchor = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                    base = f"{anchor}.{base}" if base else anchor
                for alias in node.names:
                    target = f"{base}.{alias.name}"
                    edges.add(target if target in paths else base)
        graph[name] = {edge for edge in edges if edge in paths and edge != name}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm, iterative), each as one cycle
    through its modules, in import order."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(cycle_through(graph, set(component)))
    return found


def cycle_through(graph: dict[str, set[str]], component: set[str]) -> list[str]:
    """One cycle inside a strongly connected component, from its first module back to it (breadth first)."""
    start = min(component)
    previous: dict[str, str] = {}
    frontier = [start]
    while frontier:
        following = []
        for node in frontier:
            for child in sorted(graph[node] & component):
                if child == start:
                    path = [node]
                    while path[-1] != start:
                        path.append(previous[path[-1]])
                    return [*reversed(path), start]
                if child not in previous:
                    previous[child] = node
                    following.append(child)
        frontier = following
    raise AssertionError(f"{sorted(component)} holds no cycle")


def test_the_cycle_finder_names_a_cycle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a", "d"}, "d": set(), "e": {"e2"}, "e2": set()}
    assert cycles(graph) == [["a", "b", "c", "a"]]


def test_no_module_imports_itself_back():
    """Per module, imports inside functions included: a cycle hidden by a lazy import is still a cycle."""
    graph = module_graph()
    assert "export.gate" in graph and "rafd.cli.main" in graph  # the graph holds the modules
    found = cycles(graph)
    assert not found, "import cycles:\n" + "\n".join(" -> ".join(cycle) for cycle in found)
