"""Dependencies point one way: the model knows no device, driver or node; drivers and replay know no DSP.

Two checks each: what a fresh interpreter has loaded after importing a module (catches an import
chain), and every import statement in the source, at any depth (catches a lazy import inside a
function, which importing the module never runs).
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: Where each layer's import package lives in the checkout. One top-level name is installed,
#: ``supramodal``; the node, drivers, replay and benchmarks sit beside the model in the repository
#: and install as its subpackages (pyproject.toml's package-dir).
LAYER_DIRS = {"supramodal.node": "node", "supramodal.drivers": "drivers", "supramodal.replay": "replay",
              "supramodal.benchmarks": "benchmarks", "supramodal": "supramodal"}
#: Layers the model package must never load: the node, the drivers and replay (the sources), the
#: benchmarks (which measure the node), and the device libraries.
NOT_IN_THE_MODEL = ("node", "drivers", "replay", "benchmarks", "serial", "sounddevice", "_sounddevice")
#: What drivers and replay may use of the model package: the error root, the bounded JSON reader
#: (file handling, no DSP; the model's own files need it too, so it cannot live in replay) and the
#: validation vocabulary (a driver's spec states its keys in it; pure Python, no DSP), and Ctrl-C held over
#: an optional import (a driver's device library: pylsl, sounddevice, rclpy; the standard library only).
DRIVER_MAY_USE = ("supramodal.errors", "supramodal.jsondata", "supramodal.checks", "supramodal.interrupts",
                  "supramodal.logs")


def layer(name: str) -> str:
    """The layer a dotted module name belongs to: ``supramodal.node.runtime.graph`` -> ``node``,
    ``supramodal.gammatone`` -> ``supramodal``, ``numpy.linalg`` -> ``numpy``."""
    for package in LAYER_DIRS:   # the subpackages before the model package that holds them
        if name == package or name.startswith(package + "."):
            return package.rsplit(".", 1)[-1]
    return name.split(".")[0]


def modules_of(layer_name: str) -> list[str]:
    """Every module of a layer (``"supramodal"``, ``"node"``, ...) in this checkout, by its installed
    dotted name (``__main__`` modules, which run rather than define, left out)."""
    package = "supramodal" if layer_name == "supramodal" else f"supramodal.{layer_name}"
    folder = ROOT / LAYER_DIRS[package]
    names = []
    for path in sorted(folder.rglob("*.py")):
        parts = path.relative_to(folder).with_suffix("").parts
        if parts[-1] == "__main__":
            continue
        names.append(".".join((package,) + (parts[:-1] if parts[-1] == "__init__" else parts)))
    return names


def path_of(module: str) -> Path:
    """The source file of a module of this checkout, from its installed dotted name."""
    package = next(p for p in LAYER_DIRS if module == p or module.startswith(p + "."))
    path = ROOT / LAYER_DIRS[package] / module[len(package):].lstrip(".").replace(".", "/")
    return path / "__init__.py" if path.is_dir() else path.with_suffix(".py")


def imports_in(path: Path, package: str | None = None) -> list[tuple[int, str]]:
    """``(line, imported module)`` for every import statement in a source file, at any depth: the
    absolute ones, and, given the file's ``package`` (its dotted name), the relative ones resolved
    against it (``from ..scene import build`` in ``supramodal.node.runtime`` names
    ``supramodal.node.scene.build``)."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and (node.level == 0 and node.module or node.level and package):
            target = node.module
            if node.level:
                parts = package.split(".")
                target = ".".join(parts[:len(parts) - node.level + 1] + ([node.module] if node.module else []))
            # "from supramodal import banks" imports supramodal.banks: name both
            out += [(node.lineno, target)] + [(node.lineno, f"{target}.{a.name}") for a in node.names]
    return out


def package_of(module: str) -> str:
    """The package a module of this checkout is in (a package's ``__init__`` is in the package itself),
    against which its relative imports are resolved."""
    return module if path_of(module).name == "__init__.py" else module.rsplit(".", 1)[0]


def source_imports(module: str) -> list[tuple[str, int, str]]:
    """``(file, line, imported module)`` for every import statement in a module of this checkout."""
    path = path_of(module)
    return [(str(path.relative_to(ROOT)), line, what) for line, what in imports_in(path, package_of(module))]


def loaded_after_import(modules: list[str]) -> dict[str, list[str]]:
    """For each module in turn, imported in one fresh interpreter from this checkout: the modules it
    added to ``sys.modules`` (itself and all it pulled in that an earlier one had not)."""
    code = (
        "import json, sys, importlib\n"
        "out = {}\n"
        "for name in json.loads(sys.argv[1]):\n"
        "    before = set(sys.modules)\n"
        "    module = importlib.import_module(name)\n"
        "    out[name] = {'file': module.__file__, 'added': sorted(set(sys.modules) - before)}\n"
        "print(json.dumps(out))\n"
    )
    r = subprocess.run([sys.executable, "-c", code, json.dumps(modules)], cwd=ROOT, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    for name, got in out.items():   # an editable install of another checkout must not stand in for this one
        assert Path(got["file"]).resolve().is_relative_to(ROOT), (name, got["file"])
    return {name: got["added"] for name, got in out.items()}


def test_the_checks_see_every_module_and_lazy_imports(tmp_path):
    model = modules_of("supramodal")
    assert {"supramodal", "supramodal.gammatone", "supramodal.training", "supramodal.experiments.common"} <= set(model)
    assert not any(m.startswith("supramodal.bench") for m in model)
    lazy = tmp_path / "lazy.py"
    lazy.write_text("import numpy\n\ndef f():\n    from supramodal.node.runtime.graph import Node\n"
                    "    from supramodal.drivers import base\n")
    assert imports_in(lazy) == [(1, "numpy"), (4, "supramodal.node.runtime.graph"), (4, "supramodal.node.runtime.graph.Node"),
                                (5, "supramodal.drivers"), (5, "supramodal.drivers.base")]
    assert [layer(m) for _, m in imports_in(lazy)] == ["numpy", "node", "node", "drivers", "drivers"]
    assert path_of("supramodal.node.runtime.graph") == ROOT / "node" / "runtime" / "graph.py"
    # What the bench loads (it measures the node): the import check sees a chain.
    assert "supramodal.node.runtime.graph" in loaded_after_import(["supramodal.benchmarks.filterbank.run"])["supramodal.benchmarks.filterbank.run"]


def test_importing_any_model_module_loads_no_driver_node_benchmark_or_device():
    modules = modules_of("supramodal")
    for name, added in loaded_after_import(modules).items():
        bad = sorted(m for m in added if layer(m) in NOT_IN_THE_MODEL)
        assert not bad, f"importing {name} loads {bad}"


def test_no_model_module_imports_a_driver_node_benchmark_or_device_even_lazily():
    bad = [(m, f, line, what) for m in modules_of("supramodal") for f, line, what in source_imports(m)
           if layer(what) in NOT_IN_THE_MODEL]
    assert not bad, bad


def driver_may_use(name: str) -> bool:
    """Whether a driver or replay module may import ``name`` (a module, or a name in one)."""
    if layer(name) not in ("supramodal", "node", "benchmarks"):
        return True
    return name == "supramodal" or any(name == m or name.startswith(m + ".") for m in DRIVER_MAY_USE)


@pytest.mark.parametrize("package", ["drivers", "replay"])
def test_drivers_and_replay_use_nothing_of_the_model_but_its_error_root(package):
    modules = modules_of(package)
    bad = [(m, f, line, what) for m in modules for f, line, what in source_imports(m) if not driver_may_use(what)]
    assert not bad, bad
    for name, added in loaded_after_import(modules).items():
        loaded = sorted(m for m in added if not driver_may_use(m))
        assert not loaded, f"importing {name} loads {loaded}"


def test_the_node_trains_with_the_model_layer_not_the_research_harness():
    """Only the CLI's ``experiment`` command runs the experiments; the node's training, on the spot
    or from a manifest, uses :mod:`supramodal.training`."""
    bad = [(m, f, line, what) for m in modules_of("node") if not m.startswith("supramodal.node.cli") for f, line, what in source_imports(m)
           if what.startswith("supramodal.experiments")]
    assert not bad, bad


def test_no_private_name_is_imported_from_another_module():
    """A helper another module needs is public (named and documented as such), not a private one kept
    alive for an import."""
    bad = [(m, f, line, what) for package in ("supramodal", "node", "drivers", "replay", "benchmarks")
           for m in modules_of(package) for f, line, what in source_imports(m)
           if any(part.startswith("_") and not part.startswith("__") for part in what.split("."))]
    assert not bad, bad


def test_the_wheel_installs_one_top_level_package_and_every_package_of_the_checkout():
    """Generic top-level names (node, drivers) would clash with other installed packages: the wheel
    holds ``supramodal`` alone, and every package directory of the checkout is listed in it (a new
    subpackage left out of pyproject.toml would be missing from a user's install)."""
    import tomllib

    setup = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    listed = set(setup["packages"])
    assert {p.split(".")[0] for p in listed} == {"supramodal"}
    assert setup["package-dir"] == {p: d for p, d in LAYER_DIRS.items()}
    found = set()
    for package, folder in LAYER_DIRS.items():
        for init in (ROOT / folder).rglob("__init__.py"):
            sub = init.parent.relative_to(ROOT / folder).parts
            found.add(".".join((package,) + sub))
    assert found == listed, (sorted(found - listed), sorted(listed - found))


#: The model's modules that every layer may use (docs/architecture.md: ``supramodal_shared``).
SHARED = DRIVER_MAY_USE
#: Layers from the top down: an arrow may only point down.
RANKS = ("cli", "benchmarks", "node", "replay", "drivers", "supramodal", "supramodal_shared")
#: The command line: a thin layer over all the others (it runs the benchmarks and experiments too).
CLI = ("supramodal.node.cli",)


def drawn_arrows() -> set[tuple[str, str]]:
    """The arrows of docs/architecture.md's picture (its mermaid graph)."""
    import re

    text = (ROOT / "docs/architecture.md").read_text()
    block = re.search(r"```mermaid\n(.*?)```", text, re.S).group(1)
    return set(re.findall(r"^\s*(\w+) --> (\w+)\s*$", block, re.M))


def box(module: str) -> str:
    """The box of docs/architecture.md's picture a module of this checkout sits in."""
    if any(module == m or module.startswith(m + ".") for m in SHARED):
        return "supramodal_shared"
    if any(module == m or module.startswith(m + ".") for m in CLI):
        return "cli"
    return layer(module)


def test_the_architecture_picture_is_the_imports():
    """docs/architecture.md draws every arrow the code has between layers, and no arrow points up."""
    drawn = drawn_arrows()
    assert drawn and all(RANKS.index(a) < RANKS.index(b) for a, b in drawn), drawn
    found = set()
    for package in ("benchmarks", "node", "replay", "drivers", "supramodal"):
        for m in modules_of(package):
            for _, _, what in source_imports(m):
                a, b = box(m), box(what)
                if a != b and b in RANKS:
                    found.add((a, b))
    # "supramodal" holds "supramodal_shared": an arrow to the model covers its shared modules.
    covered = drawn | {(a, "supramodal_shared") for a, b in drawn if b == "supramodal"}
    assert found <= covered, sorted(found - covered)


#: The rooms of the node (node/), from the bottom up: a module may import from its own room and the rooms
#: below it, never from one above (docs/architecture.md). The runtime (threads, buffers, sinks, taps) knows
#: no scene; the scene (schema, registries, builder) no workflow; the workflows no command. (node/__init__.py
#: is in no room; the benchmarks are a layer of their own above the node: RANKS.)
ROOMS = ("runtime", "scene", "workflows", "cli")


def room(module: str) -> str | None:
    """The room of node/ a dotted module name is in (``supramodal.node.scene.build`` -> ``"scene"``), or
    None (a module outside the rooms: ``supramodal.node`` itself, another layer, a library)."""
    parts = module.split(".")
    return parts[2] if parts[:2] == ["supramodal", "node"] and len(parts) > 2 and parts[2] in ROOMS else None


def imports_up(path: Path, package: str, from_room: str) -> list[tuple[int, str]]:
    """``(line, imported module)`` of every import statement in ``path`` (a module of ``package``, in
    room ``from_room``) that names a room above ``from_room``: at any depth, a lazy one in a function and
    one under ``TYPE_CHECKING`` too."""
    rank = ROOMS.index(from_room)
    return [(line, what) for line, what in imports_in(path, package)
            if (r := room(what)) is not None and ROOMS.index(r) > rank]


def back_arrows() -> list[tuple[str, int, str]]:
    """``(file, line, imported module)`` of every import in node/ that points up a room."""
    found = []
    for m in modules_of("node"):
        if room(m) is not None:
            path = path_of(m)
            found += [(str(path.relative_to(ROOT)), line, what) for line, what in imports_up(path, package_of(m), room(m))]
    return found


def test_the_rooms_of_the_node_import_only_downwards():
    """runtime < scene < workflows < cli inside node/: no room imports from a room above it, not even lazily
    or for its annotations (the last arrow up, the builder reading models from the workflows' cache, went
    when the cache moved beside the builder)."""
    unroomed = [m for m in modules_of("node") if m != "supramodal.node" and room(m) is None]
    assert not unroomed, f"modules of node/ in no room (give them one in ROOMS): {unroomed}"
    up = [f"{f}:{line} imports {what}" for f, line, what in back_arrows()]
    assert not up, "an import up the node's rooms (runtime < scene < workflows < cli): " + "; ".join(up)


def import_graph(modules: list[str]) -> dict[str, set[str]]:
    """Each of ``modules`` -> the modules among them it imports (any import statement at any depth: lazy,
    under TYPE_CHECKING, relative; ``from a import b`` counts as importing ``a.b`` where that is a module)."""
    known = set(modules)
    graph = {}
    for m in modules:
        targets = set()
        for _, what in imports_in(path_of(m), package_of(m)):
            while what and what not in known:
                what = what.rpartition(".")[0]
            if what and what != m:
                targets.add(what)
        graph[m] = targets
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm, iterative): each a set
    of modules that import one another round a cycle."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            v, children = work[-1]
            w = next(children, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph.get(w, ())))))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                component = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    component.append(w)
                    if w == v:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def test_no_modules_import_one_another_round_a_cycle():
    """No import cycle among the modules of every layer, counting lazy and TYPE_CHECKING imports: a cycle
    is two modules that each need the other (the builder and the model cache, the sources and the recorder
    that set itself on them, the experiments and their report were three), which no layer order shows."""
    modules = [m for layer_name in ("supramodal", "drivers", "replay", "node", "benchmarks")
               for m in modules_of(layer_name)]
    assert not cycles(import_graph(modules)), cycles(import_graph(modules))


def test_the_cycle_check_finds_a_cycle():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set(), "c": {"c"}}) == []
    assert sorted(cycles({"a": {"b"}, "b": {"a"}, "c": {"d"}, "d": {"c", "a"}})) == [["a", "b"], ["c", "d"]]


def test_the_room_check_sees_lazy_type_checking_and_relative_imports_up(tmp_path):
    fake = tmp_path / "fake.py"
    fake.write_text("from typing import TYPE_CHECKING\n\nfrom supramodal.node.runtime.clock import ClockModel\n\n"
                    "if TYPE_CHECKING:\n    from supramodal.node.scene.specs import Scene\n\n\n"
                    "def f():\n    import supramodal.node.cli.run\n    from supramodal.node.workflows import labels\n"
                    "    from ...scene import build\n    from .. import clock\n")
    package = "supramodal.node.runtime.taps"     # as if it were node/runtime/taps/fake.py
    assert sorted(imports_up(fake, package, "runtime")) == [
        (6, "supramodal.node.scene.specs"), (6, "supramodal.node.scene.specs.Scene"), (10, "supramodal.node.cli.run"),
        (11, "supramodal.node.workflows"), (11, "supramodal.node.workflows.labels"), (12, "supramodal.node.scene"),
        (12, "supramodal.node.scene.build")]
    assert imports_up(fake, package, "workflows") == [(10, "supramodal.node.cli.run")]
    assert imports_up(fake, package, "cli") == []
    assert (13, "supramodal.node.runtime.clock") in imports_in(fake, package)
    assert room("supramodal.node.runtime.sinks.spec") == "runtime" and room("supramodal.node") is None


def test_a_node_that_runs_a_model_loads_neither_scipy_signal_nor_scipy_optimize():
    """What `supramodal run` imports to build and run a scene with a model file (the CLI, the scene, the
    graph, the replay and serial drivers, the model) leaves out scipy.signal (0.6 s to import, with
    scipy.stats behind it) and scipy.optimize (0.3 s): a node process started in 1.25 s with them, 0.6 s
    without. Only resampling, the reference filterbank, the two-sense world and the fits need them."""
    code = ("import sys\n"
            "import supramodal.node.cli, supramodal.node.cli.run, supramodal.node.scene.build\n"
            "import supramodal.node.runtime.graph, supramodal.replay.driver, supramodal.drivers.serial_whisker\n"
            "import supramodal.model, supramodal.pipeline, supramodal.decisions\n"
            "print(sorted(m for m in ('scipy.signal', 'scipy.optimize', 'scipy.stats') if m in sys.modules))\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]", done.stdout


def test_nothing_but_a_ros2_sink_at_work_imports_rclpy():
    """A scene loads only what it uses (README): the command line (which takes ``--ros-args`` off),
    the builder, the graph and even the ros2 sink's own module load no rclpy; a ros2 sink that is made
    does (rclpy takes 0.3 s to import, and is absent without the ros2 extra)."""
    code = ("import sys\n"
            "import supramodal.node.cli, supramodal.node.cli.run, supramodal.node.scene.build\n"
            "import supramodal.node.runtime.graph, supramodal.node.runtime.sinks.ros2, supramodal.drivers.ros2\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('rclpy', 'std_msgs', 'sensor_msgs',\n"
            "                                                           'diagnostic_msgs')))\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]", done.stdout
