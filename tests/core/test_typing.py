"""Every public function of the core is annotated (issue "one source of truth", deliverable 6).

mypy runs with ``disallow_untyped_defs`` over the whole package (``.ci/typecheck``); this test
says the same for the public API without mypy: every public function and method (name not
starting with ``_``, in a module and class whose names do not either) annotates each parameter
but ``self``/``cls`` and its return.
"""

import ast
from pathlib import Path

import faceretarget

CORE = Path(faceretarget.__file__).parent


def _is_private(path: Path) -> bool:
    """A module is private when it, or a package above it, is named ``_...`` (``__init__.py``
    is the package itself)."""
    parts = path.relative_to(CORE).with_suffix("").parts
    return any(p.startswith("_") and p != "__init__" for p in parts)


def _missing(fn: ast.FunctionDef | ast.AsyncFunctionDef, method: bool) -> list[str]:
    """What ``fn`` leaves unannotated: parameter names, and "return"."""
    a = fn.args
    positional = [*a.posonlyargs, *a.args]
    is_static = any(isinstance(d, ast.Name) and d.id == "staticmethod" for d in fn.decorator_list)
    if method and not is_static and positional and positional[0].arg in ("self", "cls"):
        positional = positional[1:]
    params = [*positional, *a.kwonlyargs, *(p for p in (a.vararg, a.kwarg) if p is not None)]
    out = [p.arg for p in params if p.annotation is None]
    if fn.returns is None:
        out.append("return")
    return out


def unannotated(source: str, filename: str = "<source>") -> list[str]:
    """``file:line: name (missing ...)`` for each public function or method of a module's
    source that lacks an annotation (functions nested in functions are not public)."""
    found: list[str] = []

    def visit(body: list[ast.stmt], owner: str, method: bool) -> None:
        for node in body:
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                if node.name.startswith("_"):
                    continue
                missing = _missing(node, method)
                if missing:
                    found.append(
                        f"{filename}:{node.lineno}: {owner}{node.name} (missing {', '.join(missing)})"
                    )
            elif isinstance(node, ast.ClassDef) and not node.name.startswith("_"):
                visit(node.body, f"{owner}{node.name}.", True)
            elif isinstance(node, (ast.If, ast.Try)):  # definitions under `if`/`try` at this level
                blocks = [node.body, node.orelse]
                if isinstance(node, ast.Try):
                    blocks += [node.finalbody, *(h.body for h in node.handlers)]
                for block in blocks:
                    visit(block, owner, method)

    visit(ast.parse(source, filename).body, "", False)
    return found


def test_every_public_function_of_the_core_is_annotated():
    found = []
    for path in sorted(CORE.rglob("*.py")):
        if _is_private(path):
            continue
        rel = f"core/{path.relative_to(CORE).as_posix()}"
        found += unannotated(path.read_text(encoding="utf-8"), rel)
    assert not found, "public functions without complete annotations:\n" + "\n".join(found)


def test_the_check_sees_what_is_missing():
    source = """
def ok(a: int, *args: str, b: float = 1.0, **kw: object) -> None: ...
def no_return(a: int): ...
def no_param(a, b: int) -> int: ...
def _private(a, b): ...
class Public:
    def method(self, x) -> None: ...
    @classmethod
    def make(cls) -> "Public": ...
    @staticmethod
    def static(self) -> None: ...
    def _hidden(self, x): ...
class _Private:
    def method(self, x): ...
def outer(x: int) -> int:
    def inner(y): ...
    return x
try:
    def guarded(z) -> None: ...
except ImportError:
    pass
"""
    assert unannotated(source, "m.py") == [
        "m.py:3: no_return (missing return)",
        "m.py:4: no_param (missing a)",
        "m.py:7: Public.method (missing x)",
        "m.py:11: Public.static (missing self)",
        "m.py:19: guarded (missing z)",
    ]
    assert not _is_private(CORE / "io" / "__init__.py") and _is_private(CORE / "io" / "_common.py")
