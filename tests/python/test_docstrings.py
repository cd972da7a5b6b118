"""The package documents itself: every public function, class, method and property has a
docstring in the module (what ``help()`` shows) and in the type stubs (what an editor shows),
and the examples in the docstrings run with the output they show (doctest)."""

import ast
import doctest
import inspect
from pathlib import Path

import instpol

STUB = Path(__file__).resolve().parents[2] / "crates" / "python" / "python" / "instpol" / "__init__.pyi"


def public_objects():
    """(name, object) of every public function, class, method and property of the package."""
    out = []
    for name in instpol.__all__:
        obj = getattr(instpol, name)
        if name.startswith("__") or name in ("InputError", "FileError"):
            continue
        out.append((name, obj))
        if inspect.isclass(obj):
            for attr, member in vars(obj).items():
                if attr.startswith("_"):
                    continue
                if isinstance(member, (property, classmethod, staticmethod)) or inspect.isfunction(member):
                    out.append((f"{name}.{attr}", member))
    return out


def test_every_public_object_has_a_docstring():
    objs = public_objects()
    assert len(objs) > 20, [n for n, _ in objs]
    missing = [n for n, o in objs if not (getattr(o, "__doc__", None) or "").strip()]
    assert not missing, f"no docstring: {missing}"


def test_every_stub_definition_has_a_docstring():
    tree = ast.parse(STUB.read_text())
    missing = []
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.ClassDef)) and not node.name.startswith("_"):
            if ast.get_docstring(node) is None:
                missing.append(node.name)
    assert not missing, f"no docstring in __init__.pyi: {missing}"


def test_docstring_examples_run_as_shown():
    r = doctest.testmod(instpol, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert r.attempted >= 10, r
    assert r.failed == 0, r
