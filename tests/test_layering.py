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
    "modules": ("segs.slam", "segs.callbacks", "segs.train", "segs.evaluation", "segs.report"),
    "report": ("segs.slam", "segs.modules", "segs.raster", "segs.data", "segs.callbacks", "segs.train", "segs.evaluation"),
    # the bridge, the image logger and the evaluation see the mapper only through its contract
    "callbacks": ("segs.raster", "segs.train", "segs.evaluation", "segs.report"),
    "evaluation.py": ("segs.raster", "segs.slam", "segs.train", "segs.report"),
    # the web viewer reads the run (bridge, records, files) and the mapper through its contract;
    # it never drives SLAM, rasterizes or composes configs (segs.view, the entry point, does that)
    "viewer": ("segs.raster", "segs.slam", "segs.train", "segs.track", "segs.evaluation", "segs.report", "segs.config"),
    # the runtime between SLAM and mapping: numpy and the Frontend interface, no torch (its child
    # process imports it), never the mapper nor its callers
    "pipeline": ("segs.modules", "segs.raster", "segs.callbacks", "segs.train", "segs.track", "segs.evaluation",
                 "segs.viewer", "segs.report", "segs.config"),
    "map_points.py": ("segs.raster", "segs.slam", "segs.modules", "segs.data", "segs.callbacks", "segs.train", "segs.viewer"),
}
# what callbacks / evaluation / the viewer may import of segs.modules (records, protocol, image metrics)
MAPPER_CONTRACT = ("segs.modules.contract", "segs.modules.metrics")
# the only modules that may import the viewer: the entry points, and the config check of its group
VIEWER_USERS = ("train.py", "track.py", "view.py", "config.py")
def _imports(path: Path) -> list[str]:
    tree = ast.parse(path.read_text())
    names = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.append(node.module)
    return names


def _files(package: str) -> list[Path]:
    path = SRC / package
    return [path] if path.is_file() else sorted(path.rglob("*.py"))


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_package_does_not_import_across_the_boundary(package):
    bad = []
    for path in _files(package):
        for name in _imports(path):
            if name.startswith(FORBIDDEN[package]) and not (package == "raster" and name == "segs"):
                bad.append(f"{path.relative_to(SRC)} imports {name}")
    assert not bad, bad


@pytest.mark.parametrize("package", ["callbacks", "evaluation.py", "viewer"])
def test_bridge_evaluation_logger_and_viewer_use_only_the_mapper_contract(package):
    bad = [f"{path.relative_to(SRC)} imports {name}" for path in _files(package) for name in _imports(path)
           if name.startswith("segs.modules") and name not in MAPPER_CONTRACT]  # fmt: skip
    assert not bad, bad


def test_only_the_entry_points_import_the_viewer():
    bad = [f"{p.relative_to(SRC)} imports {name}" for p in SRC.rglob("*.py") for name in _imports(p)
           if name.startswith("segs.viewer") and p.parent.name != "viewer" and str(p.relative_to(SRC)) not in VIEWER_USERS]
    bad += [f"config.py imports {name}" for name in _imports(SRC / "config.py")
            if name.startswith("segs.viewer.") and name != "segs.viewer.config"]  # fmt: skip
    bad += [f"{p.relative_to(SRC)} imports segs.view" for p in _files("viewer") if "segs.view" in _imports(p)]
    assert not bad, bad


def _module_graph() -> dict[str, set[str]]:
    """segs module -> the segs modules it imports anywhere (function bodies and TYPE_CHECKING
    blocks included: a circle through a deferred import is still a circle of dependencies)."""
    def name(p: Path) -> str:
        parts = p.relative_to(SRC.parent).with_suffix("").parts
        return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)

    files = {name(p): p for p in SRC.rglob("*.py")}
    graph = {}
    for mod, path in files.items():
        edges = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                edges |= {a.name for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                edges |= {f"{node.module}.{a.name}" if f"{node.module}.{a.name}" in files else node.module for a in node.names}
        graph[mod] = {e for e in edges if e in files and e != mod}
    return graph


def _circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while comp[-1:] != [v]:
                comp.append(stack.pop())
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_no_import_circles():
    # TYPE_CHECKING and function-level imports count: the SLAM components receive their
    # collaborators (issue 12) instead of importing the frontend that builds them
    assert not _circles(_module_graph())


def test_no_slam_module_imports_the_frontend():
    users = [m for m, deps in _module_graph().items() if "segs.slam.orb" in deps and m.startswith("segs.slam.")]
    assert not users, users


# segs.slam's stages (docs/architecture.md): a unit imports from segs.slam only itself and the units
# of earlier layers; tracking (per frame) and backend (per keyframe) never import each other (orb.py
# wires them). The top-level modules of
# SLAM_SHARED are one unit; every subpackage or module of segs.slam must be listed here.
SLAM_SHARED = {"base", "config", "geometry", "outbox", "sensor", "state"}
SLAM_LAYERS = (
    ("native",),  # C++ kernels
    ("shared",),  # the Frontend interface and MapUpdate, parameters, sensor, geometry, outbox
    ("features",),  # per frame, ahead of tracking
    ("map", "estimation"),  # shared state; matching and optimisation shared by the stages
    ("tracking", "backend"),  # per frame; per keyframe
    ("orb_state",),  # the ORB frontend's checkpoint state (every part's records as arrays)
    ("orb", "known_poses"),  # the frontends
)


def _slam_unit(module: str) -> str:
    """segs.slam.<unit>[.<module>] -> its unit in SLAM_LAYERS ("shared" for SLAM_SHARED)."""
    name = module.split(".")[2]
    return "shared" if name in SLAM_SHARED else name


def _slam_stage_violations(graph: dict[str, set[str]]) -> list[str]:
    """Imports of graph's segs.slam modules that break SLAM_LAYERS, and units not listed there."""
    layer = {unit: i for i, units in enumerate(SLAM_LAYERS) for unit in units}
    modules = [m for m in graph if m.startswith("segs.slam.")]
    bad = [f"segs.slam unit {u!r} is not in SLAM_LAYERS" for u in sorted({_slam_unit(m) for m in modules} - set(layer))]
    for mod in modules:
        unit = _slam_unit(mod)
        for dep in sorted(graph[mod]):
            if dep.startswith("segs.slam.") and _slam_unit(dep) != unit and layer.get(_slam_unit(dep), -1) >= layer.get(unit, -1):
                bad.append(f"{mod} ({unit}) imports {dep} ({_slam_unit(dep)})")
    return bad


def test_slam_stages_import_only_earlier_stages():
    assert not _slam_stage_violations(_module_graph())


def test_the_slam_stage_rule_finds_a_violation():
    graph = {"segs.slam.map.map": {"segs.slam.features.frame", "segs.slam.geometry"},  # allowed
             "segs.slam.features.frame": {"segs.slam.geometry"},
             "segs.slam.geometry": set(),
             "segs.slam.tracking.tracker": {"segs.slam.backend.local_mapping"},  # same layer
             "segs.slam.backend.local_mapping": {"segs.slam.orb"},  # a later layer
             "segs.slam.orb": set(),
             "segs.slam.extra.x": set()}  # not listed
    assert _slam_stage_violations(graph) == [
        "segs.slam unit 'extra' is not in SLAM_LAYERS",
        "segs.slam.tracking.tracker (tracking) imports segs.slam.backend.local_mapping (backend)",
        "segs.slam.backend.local_mapping (backend) imports segs.slam.orb (orb)",
    ]


def test_the_circle_finder_finds_a_circle():
    assert _circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_files_stay_reasonably_small():
    big = [f"{p.relative_to(SRC)}: {n}" for p in SRC.rglob("*.py") if (n := len(p.read_text().splitlines())) > 650]
    assert not big, big
