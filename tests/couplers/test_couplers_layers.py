"""Who may import whom in couplers and experiments (imports read with ast, nothing is executed).

The flow runs one way: net folder -> traffic -> sensing -> the couplers proper -> experiments.

* ``couplers.errors``, ``couplers.publish``: nothing of couplers but each other (used by every room);
* ``couplers.net`` (the net folder and its import): errors, publish and net; the one exception is the
  importer's demand calibration, which runs SUMO gridlock trials: ``couplers.net.importer.demand`` imports
  ``couplers.traffic.sumo`` inside its functions only;
* ``couplers.traffic`` (the traffic simulation): errors, publish, net and traffic;
* ``couplers.sensing`` (the sensor models): errors, publish, net, traffic and sensing;
* the couplers proper at the top (``sumo_coupler``, ``scenarios``, ``frohle_scenario``): every room;
* couplers may import ``coloc.core`` (the frame and vehicle types it produces) and ``coloc.kernels`` (the
  numba row sort its V2F rows share with the estimators), never the inference or the methods, and never
  experiments;
* experiments may import coloc and couplers (``coloc`` never imports either: tests/coloc/test_layers.py);
* no cycle among the modules of couplers and experiments through their module-level imports (imports
  inside a function run late and may close a loop, as ``couplers.net.importer`` and its parts do).
"""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.coloc.test_layers import imports

ROOT = Path(__file__).resolve().parents[2]
SHARED = {"errors", "publish"}  # room "shared"
ROOMS = ("net", "traffic", "sensing")
#: room -> the couplers rooms it may import (its own included); "top" is the couplers proper
ALLOWED = {
    "shared": {"shared"},
    "net": {"shared", "net"},
    "traffic": {"shared", "net", "traffic"},
    "sensing": {"shared", "net", "traffic", "sensing"},
    "top": {"shared", "net", "traffic", "sensing", "top"},
}
#: (importer, imported): allowed upwards, inside a function only
IN_FUNCTION_EXCEPTIONS = {("couplers.net.importer.demand", "couplers.traffic.sumo")}


def _module_name(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(parts)


def modules(top: str) -> list[Path]:
    return sorted(p for p in (ROOT / top).rglob("*.py") if "__pycache__" not in p.parts)


def room_of(module: str) -> str | None:
    """The couplers room of a couplers module (None outside couplers)."""
    parts = module.split(".")
    if parts[0] != "couplers":
        return None
    if len(parts) == 1:
        return "top"
    if parts[1] in ROOMS:
        return parts[1]
    return "shared" if parts[1] in SHARED else "top"


def violations(paths=None, name=_module_name) -> list[str]:
    bad = []
    for path in (modules("couplers") + modules("experiments")) if paths is None else paths:
        me = name(path)
        mine = room_of(me)
        for mod, in_function, line in imports(path):
            where = f"{me}:{line} imports {mod}"
            top = mod.split(".")[0]
            if mine is not None:
                if top == "experiments":
                    bad.append(f"{where}: couplers never imports experiments")
                elif top == "coloc" and mod.split(".")[:2] not in (["coloc", "core"], ["coloc", "kernels"]):
                    bad.append(f"{where}: couplers imports only coloc.core and coloc.kernels of coloc")
                elif top == "couplers":
                    theirs = room_of(mod)
                    if theirs not in ALLOWED[mine] and not (in_function and (me, mod) in IN_FUNCTION_EXCEPTIONS):
                        bad.append(f"{where}: {mine} may import only {sorted(ALLOWED[mine])}")
    return bad


def module_graph() -> dict[str, set[str]]:
    """Module -> the couplers / experiments modules it imports at module level."""
    paths = modules("couplers") + modules("experiments")
    names = {_module_name(p) for p in paths}
    graph = {}
    for path in paths:
        me = _module_name(path)
        graph[me] = set()
        for mod, in_function, _ in imports(path):
            if not in_function and mod.split(".")[0] in ("couplers", "experiments") and mod != me:
                if mod not in names:
                    raise AssertionError(f"{me} imports {mod}, which is not a module here")
                graph[me].add(mod)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One cycle per back edge of a depth-first search (empty: the graph is acyclic)."""
    found, state, stack = [], {}, []

    def visit(node):
        state[node] = "open"
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == "open":
                found.append(stack[stack.index(nxt):] + [nxt])
            elif nxt not in state:
                visit(nxt)
        stack.pop()
        state[node] = "done"

    for node in sorted(graph):
        if node not in state:
            visit(node)
    return found


def test_layers():
    assert violations() == []


def test_no_import_cycles():
    assert cycles(module_graph()) == []


def test_the_layout_is_what_the_test_reads():
    names = {_module_name(p) for p in modules("couplers")}
    for room in ROOMS:
        assert f"couplers.{room}" in names
    for importer, imported in IN_FUNCTION_EXCEPTIONS:
        assert (imported, True) in {(m, f) for m, f, _ in imports(ROOT / (importer.replace(".", "/") + ".py"))}


@pytest.mark.parametrize("source, expected", [
    ("from experiments import cli\n", "couplers never imports experiments"),
    ("from couplers.sensing.perception import PerceptionParams\n", "net may import only"),
    ("def f():\n    from couplers.traffic.sumo import libsumo\n", "net may import only"),
    ("from coloc.methods.registry import METHODS\n", "couplers imports only coloc.core and coloc.kernels"),
])
def test_a_net_module_importing_upwards_is_caught(tmp_path, source, expected):
    """The checker itself: the net folder's module importing experiments, sensing, traffic or a coloc method."""
    copy = tmp_path / "folder.py"
    copy.write_text((ROOT / "couplers" / "net" / "folder.py").read_text() + "\n" + source)
    assert any(expected in v for v in violations([copy], name=lambda p: "couplers.net.folder"))


def test_a_cycle_is_caught():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c", "a"]]
    assert cycles({"a": {"b"}, "b": set()}) == []

