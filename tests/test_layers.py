"""Dependencies point down the package's layers, and no modules import each other in a loop.

The import graph is read from the source with `ast` (top-level, function-local and TYPE_CHECKING imports alike;
relative imports resolved), so an import hidden in a function to save start-up time still counts. The layers are
those of the architecture in the design notes, bottom first, with what the code showed to be a better shape:
- the support modules every layer uses (errors, interrupts, progress, memory, zlib_order, the package itself)
  sit at the bottom with config.py and executor.py;
- io/ is below database.py, not beside it: the database is written through io/files.py, and io/ reads model
  files and (read-only, io/sqlite.py) databases without database.py, so the two cannot import each other;
- cameras.py (the cameras written to the database) and workspace.py (the record of finished stages) sit with
  database.py, below the stages and eval/ that both use them;
- scenes/ sits with eval/ and study/ rather than with stereo/ and sem/: the renderer checks its scenes with
  eval's metrics (scenes/validate.py), and nothing in eval/ needs the renderer;
- pipeline.py and the stage modules (stages/) are one layer, under commands/ and cli.py.
A module may import its own layer (sem/ uses stereo's matchers, features/ the matcher), but not in a loop: between
modules, or between the packages and top-level modules of the table.
Imports made by name at run time (`importlib.import_module`, `find_spec`) are not seen here.
"""

import ast
from pathlib import Path

import pytest

import mvrecon

PACKAGE = Path(mvrecon.__file__).resolve().parent

# bottom first; a module belongs to the entry whose longest name is a prefix of its own
LAYERS = [
    ("support", ["mvrecon", "mvrecon.errors", "mvrecon.interrupts", "mvrecon.progress", "mvrecon.memory",
                 "mvrecon.zlib_order", "mvrecon.config", "mvrecon.executor", "mvrecon.cluster",
                 "mvrecon.startup"]),
    ("geometry", ["mvrecon.geometry"]),
    ("io", ["mvrecon.io"]),
    ("database", ["mvrecon.database", "mvrecon.cameras", "mvrecon.workspace"]),
    ("front end", ["mvrecon.features", "mvrecon.matching"]),
    ("sfm", ["mvrecon.sfm"]),
    ("stereo, sem, dense", ["mvrecon.stereo", "mvrecon.sem", "mvrecon.dense"]),
    ("eval, study, scenes", ["mvrecon.eval", "mvrecon.study", "mvrecon.scenes"]),
    ("stages", ["mvrecon.stages", "mvrecon.pipeline"]),
    ("commands", ["mvrecon.commands", "mvrecon.cli"]),
]


def module_files(root: Path) -> dict[str, Path]:
    """Dotted module name -> file, for every .py under the package folder `root` (a package by its __init__)."""
    out = {}
    for path in sorted(root.rglob("*.py")):
        parts = list(path.relative_to(root.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def import_graph(root: Path) -> dict[str, list[tuple[str, int]]]:
    """module -> [(imported module of the package, line)], every import statement in the module's source."""
    files = module_files(root)
    top = root.name

    def known(name: str) -> str | None:  # the module itself, or the package or module that defines the name
        while name and name not in files:
            name = name.rpartition(".")[0]
        return name or None

    graph = {}
    for module, path in files.items():
        package = module if path.name == "__init__.py" else module.rpartition(".")[0]
        edges = []
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join(anchor + ([node.module] if node.module else []))
                # `from pkg import name` imports the module pkg.name when there is one, else pkg
                names = [f"{base}.{a.name}" if f"{base}.{a.name}" in files else base for a in node.names]
            else:
                continue
            for name in names:
                if name == top or name.startswith(top + "."):
                    target = known(name)
                    if target and target != module and (target, node.lineno) not in edges:
                        edges.append((target, node.lineno))
        graph[module] = edges
    return graph


def layer_of(module: str, layers=LAYERS) -> tuple[int, str] | None:
    """(layer index, the table entry) of a module: its longest matching entry; None when no entry covers it."""
    best = None
    for index, (_, entries) in enumerate(layers):
        for entry in entries:
            if (module == entry or module.startswith(entry + ".")) and (best is None or len(entry) > len(best[1])):
                best = (index, entry)
    return best


def upward_imports(graph, layers=LAYERS) -> list[str]:
    """Each import of a higher layer, as 'module (line N) imports target: layer a under layer b'."""
    out = []
    for module, edges in sorted(graph.items()):
        own = layer_of(module, layers)
        for target, line in edges:
            other = layer_of(target, layers)
            if own and other and other[0] > own[0]:
                out.append(f"{module} (line {line}) imports {target}: layer '{layers[own[0]][0]}' is under "
                           f"'{layers[other[0]][0]}'")
    return out


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected groups of more than one node (Tarjan), each sorted: the loops of the graph."""
    index, low, stack, on_stack, out = {}, {}, [], set(), []

    def visit(node):
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for nxt in sorted(edges.get(node, ())):
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in on_stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            group = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                group.append(member)
                if member == node:
                    break
            if len(group) > 1:
                out.append(sorted(group))

    for node in sorted(edges):
        if node not in index:
            visit(node)
    return out


def import_loops(graph, layers=LAYERS) -> list[str]:
    """Loops between modules, and between the table's entries (io/ and database.py, say), each with the
    imports that close it."""
    out = []
    modules = {m: {t for t, _ in edges} for m, edges in graph.items()}
    for group in cycles(modules):
        links = [f"{m} -> {t} (line {line})" for m in group for t, line in graph[m] if t in group]
        out.append("modules in a loop: " + "; ".join(links))
    unit = {m: (layer_of(m, layers) or (None, m))[1] for m in graph}
    units: dict[str, set[str]] = {}
    for m, targets in modules.items():
        units.setdefault(unit[m], set()).update(unit.get(t, t) for t in targets if unit.get(t, t) != unit[m])
    for group in cycles(units):
        links = [f"{m} -> {t} (line {line})" for m in sorted(graph) if unit[m] in group
                 for t, line in graph[m] if unit.get(t, t) in group and unit.get(t, t) != unit[m]]
        out.append(f"{', '.join(group)} import each other: " + "; ".join(links))
    return out


@pytest.fixture(scope="module")
def graph():
    return import_graph(PACKAGE)


def test_every_module_has_a_layer(graph):
    missing = sorted(m for m in graph if layer_of(m) is None)
    assert not missing, f"modules in no layer of tests/test_layers.py's LAYERS: {', '.join(missing)}"


def test_no_module_imports_a_higher_layer(graph):
    found = upward_imports(graph)
    assert not found, "imports up the layers:\n" + "\n".join(found)


def test_no_import_loops(graph):
    found = import_loops(graph)
    assert not found, "import loops:\n" + "\n".join(found)


def test_the_checks_catch_a_fake_upward_import_and_loop(tmp_path):
    """A small package with the same layers: geometry/ importing sfm/ inside a function, io/ and database.py
    importing each other, and two stereo modules importing each other, are all named."""
    root = tmp_path / "mvrecon"
    sources = {
        "__init__.py": "",
        "geometry/__init__.py": "",
        "geometry/camera.py": "def project():\n    from ..sfm import model\n    return model\n",
        "sfm/__init__.py": "",
        "sfm/model.py": "from ..geometry.camera import project\n",
        "io/__init__.py": "",
        "io/colmap_model.py": "from ..database import CAMERA_MODEL_IDS\n",
        "database.py": "from .io import colmap_model\n",
        "stereo/__init__.py": "",
        "stereo/calibrate.py": "from . import pipeline\n",
        "stereo/pipeline.py": "import mvrecon.stereo.calibrate\n",
    }
    for name, text in sources.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(text)
    fake = import_graph(root)
    assert fake["mvrecon.geometry.camera"] == [("mvrecon.sfm.model", 2)]
    assert fake["mvrecon.stereo.pipeline"] == [("mvrecon.stereo.calibrate", 1)]
    up = upward_imports(fake)
    assert up == ["mvrecon.geometry.camera (line 2) imports mvrecon.sfm.model: layer 'geometry' is under 'sfm'",
                  "mvrecon.io.colmap_model (line 1) imports mvrecon.database: layer 'io' is under 'database'"]
    loops = import_loops(fake)
    assert any("mvrecon.stereo.calibrate -> mvrecon.stereo.pipeline (line 1)" in loop for loop in loops)
    assert any(loop.startswith("mvrecon.database, mvrecon.io import each other") for loop in loops)
    assert any(loop.startswith("mvrecon.geometry, mvrecon.sfm import each other") for loop in loops)
