"""The tree's layers, read from its imports: each package imports only from its own layer or below, no service
package imports another, the lab imports no service, and no two packages import each other (directly or round a
longer cycle). Read as text with ``ast``: nothing is imported or run."""

from __future__ import annotations

import ast
import functools
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# From the ground up; a package may import its own layer and those below (docs/decisions.md, "Package layout").
LAYERS: tuple[tuple[str, ...], ...] = (
    ("schemas",),
    ("services.world", "services.policies", "services.protocol", "services.metrics"),  # the pure cores
    ("services.bus", "services.faults", "services.credentials", "services.rejects",
     "services.intake", "services.inputs"),
    ("services.runconfig", "services.envconfig", "services.process"),  # what every service process shares
    ("services.sim", "services.agent", "services.monitor", "services.air"),  # the services
    ("services.supervisor",),
    ("morph_sim",),
)
PURE = LAYERS[1]
SERVICES = LAYERS[4]
# I/O a pure core never does: a bus, an event loop, processes, sockets
NOT_IN_A_PURE_CORE = {"asyncio", "zenoh", "socket", "subprocess", "services.bus", "services.faults"}


def _package(module: str) -> tuple[str, int] | None:
    best = None
    for level, packages in enumerate(LAYERS):
        for package in packages:
            if (module == package or module.startswith(package + ".")) and (best is None or len(package) > len(best[0])):
                best = (package, level)
    return best


def _modules() -> dict[str, Path]:
    out = {}
    for top in ("schemas", "services", "morph_sim"):
        for path in (ROOT / top).rglob("*.py"):
            name = ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
            out[name] = path
    return out


def _imports(path: Path) -> list[tuple[int, str]]:
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.append((node.lineno, node.module))
    return found


@functools.cache
def _edges() -> tuple[tuple[str, str, str], ...]:
    """(importing module, where, imported module) for every import of the tree: parsed once for all the checks."""
    return tuple((name, f"{path.relative_to(ROOT)}:{line}", target)
                 for name, path in _modules().items() for line, target in _imports(path))


def test_every_module_of_the_tree_has_a_layer():
    assert [name for name in _modules() if name != "services" and _package(name) is None] == []


def test_no_package_imports_a_higher_layer():
    up = [f"{where} imports {target}" for name, where, target in _edges()
          if (me := _package(name)) and (them := _package(target)) and them[1] > me[1]]
    assert up == []


def test_no_service_imports_another_and_the_lab_imports_none():
    crossing = []
    for name, where, target in _edges():
        me, them = _package(name), _package(target)
        if them is None or them[0] not in SERVICES:
            continue
        if (me and me[0] in SERVICES and me[0] != them[0]) or name.startswith("morph_sim.lab"):
            crossing.append(f"{where} imports {target}")
    assert crossing == []


def test_the_pure_cores_do_no_io():
    io = [f"{where} imports {target}" for name, where, target in _edges()
          if (me := _package(name)) and me[0] in PURE
          and any(target == bad or target.startswith(bad + ".") for bad in NOT_IN_A_PURE_CORE)]
    assert io == []


def test_no_import_cycle_between_packages():
    # packages as the layers name them, the tool's top-level modules one by one (the CLI, the API, the runner)
    def node(module: str) -> str | None:
        found = _package(module)
        if found is None:
            return None
        if found[0] == "morph_sim":
            parts = module.split(".")
            return ".".join(parts[:2]) if len(parts) > 1 else module
        return found[0]

    graph: dict[str, set[str]] = {}
    for name, _, target in _edges():
        a, b = node(name), node(target)
        if a and b and a != b:
            graph.setdefault(a, set()).add(b)

    def reaches(start: str, goal: str) -> bool:
        seen, todo = set(), [start]
        while todo:
            here = todo.pop()
            for nxt in graph.get(here, ()):
                if nxt == goal:
                    return True
                if nxt not in seen:
                    seen.add(nxt)
                    todo.append(nxt)
        return False

    assert sorted(a for a in graph if reaches(a, a)) == []


def test_the_checks_see_an_up_import():
    # the checks above are only as good as their reading of a module: a planted import must be seen
    planted = ast.parse("from morph_sim.cli import main\n")
    (node,) = planted.body
    assert _package("services.sim.service")[1] < _package(node.module)[1]


def test_the_fork_server_preloads_only_the_running_system():
    # imported by name (importlib), so the import reading above cannot see them: the processes of a run are services
    from services.supervisor.forkserver import PRELOAD

    ours = [name for name in PRELOAD if _package(name) is not None]
    assert ours and all(_package(name)[1] < _package("services.supervisor")[1] for name in ours), PRELOAD
