"""The type stub python/exolan/_native.pyi names exactly what the built extension has: the module's functions
and constants, the Engine class's methods and properties, and, where the extension exposes a signature, the same
parameters in the same order with the same defaults."""
from __future__ import annotations

import ast
import inspect
from pathlib import Path

import pytest

native = pytest.importorskip("exolan._native")
STUB = Path(__file__).resolve().parents[1] / "python" / "exolan" / "_native.pyi"


def _params(fn: ast.FunctionDef) -> list[tuple[str, str | None]]:
    a = fn.args
    pos = a.posonlyargs + a.args
    defaults = [None] * (len(pos) - len(a.defaults)) + [ast.unparse(d) for d in a.defaults]
    out = [(p.arg, d) for p, d in zip(pos, defaults)]
    out += [(p.arg, None if d is None else ast.unparse(d)) for p, d in zip(a.kwonlyargs, a.kw_defaults)]
    return [p for p in out if p[0] not in ("self", "cls")]


def _stub():
    tree = ast.parse(STUB.read_text())
    funcs, consts, classes = {}, set(), {}
    for node in tree.body:
        if isinstance(node, ast.FunctionDef):
            funcs[node.name] = _params(node)
        elif isinstance(node, ast.AnnAssign) and not node.target.id.startswith("_"):
            consts.add(node.target.id)
        elif isinstance(node, ast.ClassDef):
            members = {}
            for item in node.body:
                if isinstance(item, ast.FunctionDef):
                    deco = {ast.unparse(d) for d in item.decorator_list}
                    kind = "property" if "property" in deco else "static" if "staticmethod" in deco else "method"
                    members[item.name] = (kind, _params(item))
            classes[node.name] = members
    return funcs, consts, classes


def _runtime_params(obj) -> list[tuple[str, str | None]] | None:
    try:
        sig = inspect.signature(obj)
    except (TypeError, ValueError):
        return None
    return [(p.name, None if p.default is inspect.Parameter.empty else repr(p.default))
            for p in sig.parameters.values() if p.name not in ("self", "cls", "$self", "$cls")]


def test_stub_file_and_marker_exist():
    assert STUB.is_file()
    assert (STUB.parent / "py.typed").is_file()


def test_module_level_names_match():
    funcs, consts, classes = _stub()
    public = {k for k in dir(native) if not k.startswith("_")}
    runtime_funcs = {k for k in public if callable(getattr(native, k)) and not inspect.isclass(getattr(native, k))}
    runtime_classes = {k for k in public if inspect.isclass(getattr(native, k))}
    runtime_consts = public - runtime_funcs - runtime_classes
    consts = consts - {"__version__"}  # dunder: not in `public`, checked below
    assert isinstance(native.__version__, str)
    assert set(funcs) == runtime_funcs
    assert set(classes) == runtime_classes
    assert consts == runtime_consts
    for name, params in funcs.items():
        rt = _runtime_params(getattr(native, name))
        if rt is not None:
            assert rt == params, name


def test_engine_members_match():
    _, _, classes = _stub()
    stub = classes["Engine"]
    cls = native.Engine
    runtime = {k: v for k, v in vars(cls).items() if not k.startswith("_")}
    assert set(stub) - {"__new__"} == set(runtime)
    for name, (kind, params) in stub.items():
        if name == "__new__":
            rt = _runtime_params(cls)
            if rt is not None:
                assert rt == params, "Engine()"
            continue
        attr = runtime[name]
        if kind == "property":
            assert inspect.isdatadescriptor(attr) and not callable(attr), f"{name} is not a property"
            continue
        assert (kind == "static") == isinstance(inspect.getattr_static(cls, name), staticmethod), name
        rt = _runtime_params(getattr(cls, name))
        if rt is not None:
            assert rt == params, f"Engine.{name}: runtime {rt}, stub {params}"
