"""Custom checks' expressions over a log's columns, evaluated safely: never Python's eval.

The educator's text is parsed with `ast` and only a small arithmetic language is accepted: numbers,
column names (and `t`, seconds of loop time), + - * / ** %, comparisons (chained), and/or/not,
and the functions in FUNCTIONS. Anything else (attributes, subscripts, lambdas, calls of other
names, strings) is refused when the scenario is loaded, with the reason. Evaluation walks the
checked tree with NumPy arrays: a column is an array, a number a scalar; a reduction (mean, max,
...) turns an array into one number. Exponents are bounded so `10 ** 10 ** 10` cannot hang the queue.
"""

from __future__ import annotations

import ast
from collections.abc import Callable
from typing import Any

import numpy as np

MAX_LENGTH = 500
MAX_NODES = 200
MAX_EXPONENT = 64.0
RESERVED = frozenset({"t", "pi"})


class ExprError(ValueError):
    pass


def _rms(a: Any) -> Any:
    return np.sqrt(np.mean(np.square(a)))


# name -> (function, number of arguments); elementwise ones keep arrays, reductions give a number
FUNCTIONS: dict[str, tuple[Callable[..., Any], int]] = {
    "abs": (np.abs, 1),
    "sqrt": (lambda a: np.sqrt(np.abs(a)), 1),
    "sin": (np.sin, 1),
    "cos": (np.cos, 1),
    "exp": (lambda a: np.exp(np.clip(a, -700, 700)), 1),
    "minimum": (np.minimum, 2),
    "maximum": (np.maximum, 2),
    "mean": (np.mean, 1),
    "max": (np.max, 1),
    "min": (np.min, 1),
    "rms": (_rms, 1),
    "std": (np.std, 1),
    "final": (lambda a: np.asarray(a).reshape(-1)[-1], 1),
}

_BINOPS: dict[type, Callable[[Any, Any], Any]] = {
    ast.Add: np.add,
    ast.Sub: np.subtract,
    ast.Mult: np.multiply,
    ast.Div: np.divide,
    ast.Mod: np.mod,
}
_CMPOPS: dict[type, Callable[[Any, Any], Any]] = {
    ast.Lt: np.less,
    ast.LtE: np.less_equal,
    ast.Gt: np.greater,
    ast.GtE: np.greater_equal,
    ast.Eq: np.equal,
    ast.NotEq: np.not_equal,
}
_ALLOWED = (
    ast.Expression,
    ast.BinOp,
    ast.UnaryOp,
    ast.BoolOp,
    ast.Compare,
    ast.Call,
    ast.Name,
    ast.Constant,
    ast.Load,
    ast.USub,
    ast.UAdd,
    ast.Not,
    ast.And,
    ast.Or,
    ast.Pow,
    *_BINOPS,
    *_CMPOPS,
)


def compile_expr(source: str) -> ast.Expression:
    """The checked tree of `source`; ExprError saying what is not allowed."""
    if not isinstance(source, str) or not source.strip():
        raise ExprError("an empty expression")
    if len(source) > MAX_LENGTH:
        raise ExprError(f"longer than {MAX_LENGTH} characters")
    try:
        tree = ast.parse(source.strip(), mode="eval")
    except SyntaxError as exc:
        raise ExprError(f"syntax error at column {exc.offset or 0}: {exc.msg}") from None
    nodes = list(ast.walk(tree))
    if len(nodes) > MAX_NODES:
        raise ExprError(f"more than {MAX_NODES} parts")
    for node in nodes:
        if not isinstance(node, _ALLOWED):
            raise ExprError(
                f"'{ast.unparse(node) if isinstance(node, ast.expr) else type(node).__name__}' is not allowed"
            )
        if isinstance(node, ast.Constant) and (
            isinstance(node.value, bool) or not isinstance(node.value, (int, float))
        ):
            raise ExprError(f"only numbers, not {node.value!r}")
        if isinstance(node, ast.Call):
            if not isinstance(node.func, ast.Name) or node.func.id not in FUNCTIONS:
                raise ExprError(f"unknown function in '{ast.unparse(node)}'; have: {', '.join(FUNCTIONS)}")
            if node.keywords or len(node.args) != FUNCTIONS[node.func.id][1]:
                raise ExprError(f"{node.func.id}() takes {FUNCTIONS[node.func.id][1]} argument(s)")
    return tree


def names(source: str) -> set[str]:
    """The column names an expression reads (not functions, not `t`/`pi`)."""
    tree = compile_expr(source)
    funcs = {id(n.func) for n in ast.walk(tree) if isinstance(n, ast.Call)}
    return {n.id for n in ast.walk(tree) if isinstance(n, ast.Name) and id(n) not in funcs} - RESERVED


def evaluate(source: str, columns: dict[str, np.ndarray]) -> Any:
    """The value of `source` over `columns` (each a float array of one length; `t` among them)."""
    tree = compile_expr(source)
    with np.errstate(all="ignore"):
        return _eval(tree.body, columns)


def _eval(node: ast.expr, cols: dict[str, np.ndarray]) -> Any:
    if isinstance(node, ast.Constant):
        assert isinstance(node.value, (int, float))  # compile_expr let only numbers through
        return float(node.value)
    if isinstance(node, ast.Name):
        if node.id == "pi":
            return float(np.pi)
        if node.id not in cols:
            raise ExprError(f"no column {node.id!r} in the log")
        return cols[node.id]
    if isinstance(node, ast.UnaryOp):
        v = _eval(node.operand, cols)
        if isinstance(node.op, ast.Not):
            return np.logical_not(v)
        return np.negative(v) if isinstance(node.op, ast.USub) else v
    if isinstance(node, ast.BinOp):
        a, b = _eval(node.left, cols), _eval(node.right, cols)
        if isinstance(node.op, ast.Pow):
            if np.any(np.abs(b) > MAX_EXPONENT):
                raise ExprError(f"an exponent above {MAX_EXPONENT:g}")
            return np.power(np.asarray(a, dtype=float), b)
        return _BINOPS[type(node.op)](a, b)
    if isinstance(node, ast.BoolOp):
        values = [_eval(v, cols) for v in node.values]
        out = values[0]
        for v in values[1:]:
            out = np.logical_and(out, v) if isinstance(node.op, ast.And) else np.logical_or(out, v)
        return out
    if isinstance(node, ast.Compare):
        left = _eval(node.left, cols)
        result: Any = True
        for op, right_node in zip(node.ops, node.comparators, strict=True):
            right = _eval(right_node, cols)
            result = np.logical_and(result, _CMPOPS[type(op)](left, right))
            left = right
        return result
    if isinstance(node, ast.Call):
        assert isinstance(node.func, ast.Name)
        fn = FUNCTIONS[node.func.id][0]
        args = [_eval(a, cols) for a in node.args]
        if node.func.id in ("mean", "max", "min", "rms", "std", "final") and np.size(args[0]) == 0:
            raise ExprError(f"{node.func.id}() of no samples")
        return fn(*args)
    raise ExprError(f"'{ast.unparse(node)}' is not allowed")
