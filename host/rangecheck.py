"""Load a pure-Python module with every arithmetic result range-checked.

The RP2040 port of MicroPython keeps ints in 31-bit small ints; any value with
|x| >= 2**30 silently becomes a heap-allocated long int. The unix port (63-bit
small ints) cannot show that, so the range is proved on CPython: every BinOp,
UnaryOp and AugAssign result of the module is wrapped in a checker that raises
`RangeError` when an int reaches 2**30 in magnitude, and records the largest
magnitude seen.
"""

from __future__ import annotations

import ast
import types
from pathlib import Path

LIMIT = 1 << 30


class RangeError(ArithmeticError):
    pass


class Tracker:
    def __init__(self, limit: int = LIMIT):
        self.limit = limit
        self.max_abs = 0
        self.where = ""
        self.checks = 0

    def __call__(self, value, where):
        if type(value) is int:
            self.checks += 1
            a = -value if value < 0 else value
            if a > self.max_abs:
                self.max_abs = a
                self.where = where
            if a >= self.limit:
                raise RangeError(f"|{value}| >= 2**30 at {where}")
        return value


class _Instrument(ast.NodeTransformer):
    def __init__(self, filename: str):
        self.filename = filename

    def _wrap(self, node: ast.expr, lineno: int) -> ast.Call:
        where = ast.Constant(f"{self.filename}:{lineno}")
        return ast.Call(func=ast.Name("__rangecheck__", ast.Load()), args=[node, where], keywords=[])

    def visit_BinOp(self, node):
        self.generic_visit(node)
        return ast.copy_location(self._wrap(node, node.lineno), node)

    def visit_UnaryOp(self, node):
        self.generic_visit(node)
        if isinstance(node.op, ast.Not):
            return node
        return ast.copy_location(self._wrap(node, node.lineno), node)

    def visit_AugAssign(self, node):
        self.generic_visit(node)
        t = node.target
        if isinstance(t, ast.Name):
            load = ast.Name(t.id, ast.Load())
        elif isinstance(t, ast.Attribute):
            load = ast.Attribute(t.value, t.attr, ast.Load())
        else:  # subscripts: evaluate the index twice, fine for pure code
            load = ast.Subscript(t.value, t.slice, ast.Load())
        value = self._wrap(ast.BinOp(load, node.op, node.value), node.lineno)
        return ast.copy_location(ast.Assign(targets=[t], value=value), node)


def load_instrumented(path: Path | str, name: str | None = None, tracker: Tracker | None = None):
    """Return (module, tracker): the module at `path`, instrumented."""
    path = Path(path)
    tracker = tracker or Tracker()
    tree = _Instrument(path.name).visit(ast.parse(path.read_text(), str(path)))
    ast.fix_missing_locations(tree)
    mod = types.ModuleType(name or path.stem)
    mod.__file__ = str(path)
    mod.__dict__["__rangecheck__"] = tracker
    exec(compile(tree, str(path), "exec"), mod.__dict__)
    return mod, tracker
