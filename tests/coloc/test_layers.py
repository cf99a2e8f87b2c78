"""Who may import whom inside coloc (imports read with ast, nothing is executed).

* ``coloc.core``: numpy and scipy, nothing else of coloc;
* ``coloc.kernels``: ``coloc.core`` and numpy / numba (llvmlite, numba's code generator) at module
  level; a kernel's numpy reference may import scipy inside its function;
* ``coloc.inference``: kernels and core;
* ``coloc.methods``: inference, kernels, core and other methods;
* nothing in coloc imports couplers, experiments, libsumo, traci or sumolib;
* gtsam only in ``coloc.methods.fg_topology``, inside a function (``if TYPE_CHECKING:`` imports,
  which never run, are for annotations and are not counted).
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

COLOC = Path(__file__).resolve().parents[2] / "coloc"
LAYERS = ("core", "kernels", "inference", "methods")
#: layer -> the coloc layers it may import (its own included)
ALLOWED = {
    "core": {"core"},
    "kernels": {"core", "kernels"},
    "inference": {"core", "kernels", "inference"},
    "methods": {"core", "kernels", "inference", "methods"},
}
FORBIDDEN = {"couplers", "experiments", "libsumo", "traci", "sumolib"}
KERNEL_MODULE_LEVEL = {"numpy", "numba", "llvmlite"}
KERNEL_IN_FUNCTION = KERNEL_MODULE_LEVEL | {"scipy"}
GTSAM_MODULE = "coloc.methods.fg_topology"


def _module_name(path: Path) -> str:
    rel = path.relative_to(COLOC.parent).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(parts)


def _is_type_checking(node: ast.If) -> bool:
    t = node.test
    return (isinstance(t, ast.Name) and t.id == "TYPE_CHECKING") or (
        isinstance(t, ast.Attribute) and t.attr == "TYPE_CHECKING")


def imports(path: Path) -> list[tuple[str, bool, int]]:
    """(imported module, inside a function, line) of every import that can run."""
    out = []

    def visit(node, in_function):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and _is_type_checking(child):
                for sub in child.orelse:
                    visit(sub, in_function)
                continue
            inner = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            if isinstance(child, ast.Import):
                out.extend((a.name, in_function, child.lineno) for a in child.names)
            elif isinstance(child, ast.ImportFrom) and child.level == 0 and child.module:
                out.append((child.module, in_function, child.lineno))
            elif isinstance(child, ast.ImportFrom):
                raise AssertionError(f"{path}:{child.lineno}: relative import (write the absolute module)")
            visit(child, inner)

    visit(ast.parse(path.read_text(), str(path)), False)
    return out


def modules():
    return sorted(p for p in COLOC.rglob("*.py") if "__pycache__" not in p.parts)


def layer_of(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[0] == "coloc" and parts[1] in LAYERS else None


def violations(paths=None) -> list[str]:
    bad = []
    for path in modules() if paths is None else paths:
        me = _module_name(path)
        mine = layer_of(me)
        if me != "coloc" and mine is None:
            bad.append(f"{me}: a module outside the layers {LAYERS}")
        for mod, in_function, line in imports(path):
            where = f"{me}:{line} imports {mod}"
            top = mod.split(".")[0]
            if top in FORBIDDEN:
                bad.append(f"{where}: coloc never imports {top}")
            if top == "gtsam" and (me != GTSAM_MODULE or not in_function):
                bad.append(f"{where}: gtsam only inside a function of {GTSAM_MODULE}")
            if top == "coloc" and mine is not None:
                theirs = layer_of(mod)
                if theirs is None and mod != "coloc":
                    bad.append(f"{where}: not a module of a layer")
                elif theirs is not None and theirs not in ALLOWED[mine]:
                    bad.append(f"{where}: {mine} may import only {sorted(ALLOWED[mine])}")
            if mine == "kernels" and top != "coloc" and top not in sys.stdlib_module_names:
                allowed = KERNEL_IN_FUNCTION if in_function else KERNEL_MODULE_LEVEL
                if top not in allowed:
                    bad.append(f"{where}: kernels import only numpy and numba (and core)")
    return bad


def test_layers():
    assert violations() == []


def test_the_layout_is_what_the_test_reads():
    names = {_module_name(p) for p in modules()}
    for layer in LAYERS:
        assert f"coloc.{layer}" in names
    assert GTSAM_MODULE in names
    assert any(mod.split(".")[0] == "gtsam" and inside for mod, inside, _ in imports(COLOC / "methods" / "fg_topology.py"))


@pytest.mark.parametrize("source, expected", [
    ("from coloc.methods.gnss import GnssTracker\n", "kernels may import only"),
    ("import gtsam\n", "gtsam only inside a function"),
    ("def f():\n    import libsumo\n", "coloc never imports libsumo"),
    ("import scipy\n", "kernels import only numpy and numba"),
])
def test_a_kernel_importing_upwards_is_caught(tmp_path, monkeypatch, source, expected):
    """The checker itself: a kernel module that imports a method, gtsam, libsumo or scipy."""
    fake = COLOC / "kernels" / "icp.py"
    text = fake.read_text() + "\n" + source
    copy = tmp_path / "icp.py"
    copy.write_text(text)
    monkeypatch.setattr(sys.modules[__name__], "_module_name", lambda p: "coloc.kernels.icp")
    assert any(expected in v for v in violations([copy]))


#: Where a method's name may also be written: the studies name their own methods (study kinds),
#: and the coupler's seeded noise stream of the GNSS fixes is called "gnss" (not the method).
NAME_ELSEWHERE = {("couplers/sensing/sensors.py", "gnss")}


def test_method_names_are_written_only_in_the_registry():
    """Each method name is a string literal (docstrings aside) in one source file outside tests:
    coloc/methods/registry.py; every other place reads the registry."""
    from coloc.methods.registry import METHODS

    root = COLOC.parent
    found = {}
    for path in sorted(p for top in ("coloc", "couplers", "experiments", "bench", "tools")
                       for p in (root / top).rglob("*.py")):
        rel = path.relative_to(root).as_posix()
        if rel.startswith("experiments/studies/"):
            continue
        tree = ast.parse(path.read_text(), rel)
        docs = {id(n.body[0].value) for n in ast.walk(tree)
                if isinstance(n, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
                and n.body and isinstance(n.body[0], ast.Expr) and isinstance(n.body[0].value, ast.Constant)}
        for node in ast.walk(tree):
            if (isinstance(node, ast.Constant) and node.value in METHODS and id(node) not in docs
                    and (rel, node.value) not in NAME_ELSEWHERE):
                found.setdefault(node.value, set()).add(rel)
    assert found == {name: {"coloc/methods/registry.py"} for name in METHODS}
