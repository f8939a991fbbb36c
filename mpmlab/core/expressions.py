"""Small, safe arithmetic expressions written once and run on NumPy, JAX and Warp.

A config (or a script) may give a body force or an initial field as one string per component, e.g.
``"A * sin(pi * X[0]) * cos(w * t)"``. The string is parsed with :mod:`ast` and only a whitelist is
accepted: numbers, the names the caller allows (a position vector indexed by a constant, ``t``,
named constants), ``pi``, the operators ``+ - * / **`` and the functions in ``FUNCTIONS``. Nothing
else (attributes, comprehensions, keywords, strings, other names) gets through, so a config cannot
run arbitrary code.

The parsed tree is then

* *interpreted* on an array module ``xp`` (``numpy`` or ``jax.numpy``): a position ``X [N, D]`` gives
  a result per point (``evaluate``);
* *translated* into the body of a Warp ``@wp.func`` (``warp_source``): every literal is wrapped in the
  scalar type (Warp does not mix float32 literals with float64 values) and named constants read a
  parameter array, so changing a constant's value does not recompile and gradients reach it.
"""
from __future__ import annotations

import ast
import math
from typing import Any, Mapping, Sequence

from .errors import ConfigError

#: name -> (NumPy/JAX function name, Warp function, arity)
FUNCTIONS = {
    "sin": ("sin", "wp.sin", 1), "cos": ("cos", "wp.cos", 1), "tan": ("tan", "wp.tan", 1),
    "asin": ("arcsin", "wp.asin", 1), "acos": ("arccos", "wp.acos", 1), "atan": ("arctan", "wp.atan", 1),
    "atan2": ("arctan2", "wp.atan2", 2), "sinh": ("sinh", "wp.sinh", 1), "cosh": ("cosh", "wp.cosh", 1),
    "tanh": ("tanh", "wp.tanh", 1), "exp": ("exp", "wp.exp", 1), "log": ("log", "wp.log", 1),
    "sqrt": ("sqrt", "wp.sqrt", 1), "abs": ("abs", "wp.abs", 1), "min": ("minimum", "wp.min", 2),
    "max": ("maximum", "wp.max", 2),
}
BUILTIN_CONSTANTS = {"pi": math.pi}
_BINOPS = {ast.Add: "+", ast.Sub: "-", ast.Mult: "*", ast.Div: "/", ast.Pow: "**"}
_UNARY = {ast.USub: "-", ast.UAdd: "+"}


class Expression:
    """One scalar expression, checked against the names it may use.

    Args:
        text: the expression (a string, or a number).
        vectors: names of position vectors (``X``, ``x``), each indexed by a constant ``0 <= k < dim``.
        scalars: names of scalar variables (``t``).
        constants: names of user constants (values supplied at evaluation; ``pi`` is built in).
        dim: the vectors' length.
        where: what the expression belongs to, for errors.
    """

    def __init__(self, text: Any, vectors: Sequence[str], scalars: Sequence[str], constants: Sequence[str],
                 dim: int, where: str):
        self.text, self.where, self.dim = text, where, dim
        self.vectors, self.scalars, self.constants = tuple(vectors), tuple(scalars), tuple(constants)
        if isinstance(text, bool) or not isinstance(text, (str, int, float)):
            raise ConfigError(f"{where}: {text!r} is not an expression (a string such as '2 * t' or a number).")
        src = str(text).strip()
        try:
            tree = ast.parse(src, mode="eval")
        except SyntaxError as e:
            raise ConfigError(f"{where}: cannot parse '{src}' ({e.msg}).") from None
        self.used: set[str] = set()
        self._check(tree.body)
        self.tree = tree.body

    # ---- validation -------------------------------------------------------------------------------
    def _bad(self, what: str):
        allowed = ", ".join([*(f"{v}[k]" for v in self.vectors), *self.scalars, *self.constants, "pi"])
        raise ConfigError(f"{self.where}: '{self.text}': {what}; an expression may use numbers, {allowed}, "
                          f"+ - * / ** and {', '.join(FUNCTIONS)}.")

    def _check(self, n: ast.AST) -> None:
        if isinstance(n, ast.Constant):
            if isinstance(n.value, bool) or not isinstance(n.value, (int, float)):
                self._bad(f"{n.value!r} is not a number")
        elif isinstance(n, ast.BinOp):
            if type(n.op) not in _BINOPS:
                self._bad(f"operator {type(n.op).__name__} is not allowed")
            self._check(n.left)
            self._check(n.right)
        elif isinstance(n, ast.UnaryOp):
            if type(n.op) not in _UNARY:
                self._bad(f"operator {type(n.op).__name__} is not allowed")
            self._check(n.operand)
        elif isinstance(n, ast.Name):
            if n.id in self.vectors:
                self._bad(f"'{n.id}' is a vector; use a component {n.id}[0]..{n.id}[{self.dim - 1}]")
            if n.id not in (*self.scalars, *self.constants, *BUILTIN_CONSTANTS):
                self._bad(f"unknown name '{n.id}'")
            self.used.add(n.id)
        elif isinstance(n, ast.Subscript):
            k = n.slice
            if not (isinstance(n.value, ast.Name) and n.value.id in self.vectors and isinstance(k, ast.Constant)
                    and isinstance(k.value, int) and not isinstance(k.value, bool)):
                self._bad("only a position component such as X[0] may be indexed")
            if not 0 <= k.value < self.dim:
                self._bad(f"component {n.value.id}[{k.value}] does not exist in {self.dim}D")
            self.used.add(n.value.id)
        elif isinstance(n, ast.Call):
            f = n.func.id if isinstance(n.func, ast.Name) else None
            if f not in FUNCTIONS:
                self._bad(f"'{ast.unparse(n.func)}' is not an allowed function")
            if n.keywords:
                self._bad(f"{f} takes positional arguments only")
            if len(n.args) != FUNCTIONS[f][2]:
                self._bad(f"{f} takes {FUNCTIONS[f][2]} argument(s)")
            for a in n.args:
                self._check(a)
        else:
            self._bad(f"'{ast.unparse(n)}' ({type(n).__name__}) is not allowed")

    # ---- NumPy / JAX ------------------------------------------------------------------------------
    def evaluate(self, xp, env: Mapping[str, Any], n: int | None = None):
        """The value with ``env`` (vectors ``[N, D]``, scalars, constants by name); with ``n``, broadcast to
        ``[n]`` (a constant expression otherwise stays a scalar)."""
        out = self._eval(self.tree, xp, env)
        if n is not None and xp.ndim(out) == 0:
            out = xp.zeros(n) + out
        return out

    def _eval(self, n, xp, env):
        if isinstance(n, ast.Constant):
            return float(n.value)
        if isinstance(n, ast.BinOp):
            a, b = self._eval(n.left, xp, env), self._eval(n.right, xp, env)
            op = type(n.op)
            return (a + b if op is ast.Add else a - b if op is ast.Sub else a * b if op is ast.Mult
                    else a / b if op is ast.Div else a ** b)
        if isinstance(n, ast.UnaryOp):
            a = self._eval(n.operand, xp, env)
            return -a if isinstance(n.op, ast.USub) else a
        if isinstance(n, ast.Name):
            return BUILTIN_CONSTANTS[n.id] if n.id in BUILTIN_CONSTANTS and n.id not in env else env[n.id]
        if isinstance(n, ast.Subscript):
            return env[n.value.id][..., n.slice.value]
        f = FUNCTIONS[n.func.id][0]
        return getattr(xp, f)(*(self._eval(a, xp, env) for a in n.args))

    # ---- Warp ------------------------------------------------------------------------------------
    def warp_source(self, constant_index: Mapping[str, str], scalar: str = "S") -> str:
        """Warp source of the expression: literals as ``scalar(...)``, constants as ``constant_index[name]``
        (e.g. ``"p[3]"``), vectors and scalars by their own names."""
        return self._warp(self.tree, constant_index, scalar)

    def _warp(self, n, ci, S):
        if isinstance(n, ast.Constant):
            return f"{S}({float(n.value)!r})"
        if isinstance(n, ast.BinOp):
            a, b = self._warp(n.left, ci, S), self._warp(n.right, ci, S)
            return f"wp.pow({a}, {b})" if isinstance(n.op, ast.Pow) else f"({a} {_BINOPS[type(n.op)]} {b})"
        if isinstance(n, ast.UnaryOp):
            return f"({_UNARY[type(n.op)]}{self._warp(n.operand, ci, S)})"
        if isinstance(n, ast.Name):
            if n.id in ci:
                return ci[n.id]
            if n.id in BUILTIN_CONSTANTS:
                return f"{S}({BUILTIN_CONSTANTS[n.id]!r})"
            return n.id
        if isinstance(n, ast.Subscript):
            return f"{n.value.id}[{n.slice.value}]"
        return f"{FUNCTIONS[n.func.id][1]}({', '.join(self._warp(a, ci, S) for a in n.args)})"


def is_expression(v: Any) -> bool:
    """True for a string, or a (nested) list holding at least one string: an expression form."""
    if isinstance(v, str):
        return True
    if isinstance(v, (list, tuple)):
        return any(is_expression(e) for e in v)
    return False


def parse_components(value: Any, shape: tuple[int, ...], where: str, **kw) -> list:
    """A nested list of ``Expression`` of ``shape`` (``(D,)`` or ``(D, D)``) from nested lists of strings
    and numbers; a wrong nesting is refused with the expected shape."""
    if not shape:
        return Expression(value, where=where, **kw)
    if not isinstance(value, (list, tuple)) or len(value) != shape[0]:
        raise ConfigError(f"{where}: {value!r} must be a list of {shape[0]} entries (shape {list(shape)}), "
                          f"each a number or an expression string.")
    return [parse_components(v, shape[1:], f"{where}[{i}]", **kw) for i, v in enumerate(value)]
