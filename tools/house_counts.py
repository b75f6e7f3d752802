"""How big the package's rooms are: modules, classes and functions over the house's bounds.

Usage::

    python tools/house_counts.py [--list] [PACKAGE_DIR]

Counts, in product code (``optitac_edge/``): modules over 500 lines, classes
with more than 15 methods, functions over 60 lines (the ``def`` line to the
last line of its body; the list also says how many without the docstring) and functions with more than 8 parameters (``self``
and ``cls`` not counted). ``--list`` names each.
"""

from __future__ import annotations

import argparse
import ast
from pathlib import Path

MODULE_LINES, CLASS_METHODS, FUNCTION_LINES, PARAMETERS = 500, 15, 60, 8


def _params(fn: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    a = fn.args
    names = [p.arg for p in (*a.posonlyargs, *a.args, *a.kwonlyargs)]
    names += [p.arg for p in (a.vararg, a.kwarg) if p is not None]
    return len([n for n in names if n not in ("self", "cls")])


def _docstring_lines(fn: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    first = fn.body[0] if fn.body else None
    if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(first.value.value, str):
        return (first.end_lineno or first.lineno) - first.lineno + 1
    return 0


def count(root: Path) -> dict[str, list[str]]:
    """Each bound's offenders, as ``path:line name (figure)``."""
    out: dict[str, list[str]] = {"modules": [], "classes": [], "long functions": [], "many parameters": []}
    for path in sorted(root.rglob("*.py")):
        text = path.read_text()
        rel = path.relative_to(root.parent)
        lines = text.count("\n") + 1
        if lines > MODULE_LINES:
            out["modules"].append(f"{rel} ({lines} lines)")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.ClassDef):
                methods = [n for n in node.body if isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef)]
                if len(methods) > CLASS_METHODS:
                    out["classes"].append(f"{rel}:{node.lineno} {node.name} ({len(methods)} methods)")
            elif isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                length = (node.end_lineno or node.lineno) - node.lineno + 1
                if length > FUNCTION_LINES:
                    out["long functions"].append(f"{rel}:{node.lineno} {node.name} ({length} lines, "
                                                 f"{length - _docstring_lines(node)} without its docstring)")
                if _params(node) > PARAMETERS:
                    out["many parameters"].append(f"{rel}:{node.lineno} {node.name} ({_params(node)} parameters)")
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("package", nargs="?", type=Path, default=Path(__file__).resolve().parents[1] / "optitac_edge")
    ap.add_argument("--list", action="store_true", help="name every offender")
    args = ap.parse_args()
    found = count(args.package)
    for kind, items in found.items():
        print(f"{kind}: {len(items)}")
        if args.list:
            for item in items:
                print(f"  {item}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
