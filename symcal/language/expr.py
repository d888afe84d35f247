"""The expression language of symcal model and problem files.

Expressions such as ``k0 + k1*sin(f*p)`` or ``(s1.p_hat - s3.p_hat)/l_s`` are read by a
hand-written tokenizer and a Pratt parser into a small immutable AST, which is then built
into CasADi SX (:func:`to_casadi`) or evaluated in pure Python (:func:`evaluate`). Python's
``eval``/``compile`` are never used, so the text cannot reach Python objects.

Grammar, lowest to highest precedence: ``+ -`` (left), ``* /`` (left), unary ``- +``,
``**`` (right; its right operand may start with a unary sign, so ``2**-1 == 0.5`` and
``-2**2 == -4``). Atoms: numbers (``1``, ``.5``, ``2.``, ``1.5E+3``), names with at most
one dot (``s1.p_hat``), the constant ``pi``, parenthesised expressions and calls of the
functions in :data:`FUNCTIONS`. A name is a call exactly when ``(`` follows it.

Errors are reported in this order: the length limit, then problems in the characters
(unexpected character, malformed number, bad dotted name, unknown function), scanning left
to right, then syntax errors (unexpected token, arity, nesting depth).

Nesting is limited so that no input can exhaust Python's stack: every parenthesis, call,
unary sign and right operand of an operator enclosing a position opens one level, and the
AST may be at most :data:`MAX_DEPTH` operators high (which bounds ``1+1+...+1``).
"""

from __future__ import annotations

import functools
import math
import operator
import re
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import casadi

from symcal.base.didyoumean import did_you_mean
from symcal.base.errors import SymcalError

#: Function name -> number of arguments.
FUNCTIONS: dict[str, int] = {
    **dict.fromkeys(
        ["sin", "cos", "tan", "asin", "acos", "atan", "sqrt", "exp", "log", "abs",
         "sinh", "cosh", "tanh"],
        1,
    ),
    "atan2": 2,
}
#: Names a model or problem cannot declare: the constant and the functions.
RESERVED_NAMES = frozenset({"pi", *FUNCTIONS})
#: Longest accepted expression, in characters.
MAX_LENGTH = 20_000
#: Deepest accepted nesting of parentheses, calls, unary and binary operators (see above).
MAX_DEPTH = 100


class ExprError(SymcalError):
    """A problem with an expression's text.

    Parameters
    ----------
    detail
        The message, without file or position prefix; ``str(err) == detail``.
    column
        0-based column of the offending character, or None.
    symbol
        The offending name (e.g. an unknown function), or None.
    """

    def __init__(self, detail: str, column: int | None = None, symbol: str | None = None):
        super().__init__(detail)
        self.detail = detail
        self.column = column
        self.symbol = symbol


@dataclass(frozen=True)
class Num:
    """A number literal (``pi`` parses to ``Num(math.pi)``)."""

    value: float
    col: int = field(default=0, compare=False)


@dataclass(frozen=True)
class Name:
    """A symbol, possibly dotted once (``s1.p_hat``)."""

    name: str
    col: int = field(default=0, compare=False)


@dataclass(frozen=True)
class Unary:
    """A unary operator (``-``; the parser drops unary ``+``)."""

    op: str
    operand: Node
    col: int = field(default=0, compare=False)


@dataclass(frozen=True)
class Binary:
    """A binary operator: one of ``+ - * / **``."""

    op: str
    left: Node
    right: Node
    col: int = field(default=0, compare=False)


@dataclass(frozen=True)
class Call:
    """A call of one of :data:`FUNCTIONS`."""

    func: str
    args: tuple[Node, ...]
    col: int = field(default=0, compare=False)


Node = Num | Name | Unary | Binary | Call

# ---------------------------------------------------------------------------- tokenizer


class _Tok(NamedTuple):
    kind: str  # "num", "name", "func", "op", "end"
    text: str
    col: int
    value: float = 0.0


_DIGITS = frozenset("0123456789")
_IDENT_START = frozenset("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ_")
_IDENT = _IDENT_START | _DIGITS
_SPACE = frozenset(" \t\r\n")
_NUMBER = re.compile(r"(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")


def _char_error(ch: str, col: int) -> ExprError:
    shown = ch if ch.isprintable() else repr(ch)[1:-1]
    return ExprError(f"unexpected character '{shown}' at column {col + 1}", col)


def _tokenize(text: str) -> list[_Tok]:
    toks: list[_Tok] = []
    i, n = 0, len(text)
    while i < n:
        ch = text[i]
        start = i
        if ch in _SPACE:
            i += 1
        elif ch in _DIGITS or (ch == "." and i + 1 < n and text[i + 1] in _DIGITS):
            # Take the whole number-like run, then validate it, so "1e" or "1.2.3" is one error.
            while i < n and (text[i] in _IDENT or text[i] == "."
                             or (text[i] in "+-" and text[i - 1] in "eE")):
                i += 1
            span = text[start:i]
            if not _NUMBER.fullmatch(span):
                raise ExprError(f"malformed number '{span}' at column {start + 1}", start)
            toks.append(_Tok("num", span, start, float(span)))
        elif ch in _IDENT_START:
            parts = []
            while True:
                j = i
                while i < n and text[i] in _IDENT:
                    i += 1
                parts.append(text[j:i])
                if i < n and text[i] == ".":
                    if i + 1 < n and text[i + 1] in _IDENT_START:
                        i += 1
                        continue
                    raise _char_error(".", i)
                break
            name = ".".join(parts)
            if len(parts) > 2:
                raise ExprError(f"names may contain at most one dot: '{name}'", start, name)
            k = i
            while k < n and text[k] in _SPACE:
                k += 1
            if k < n and text[k] == "(":
                if name == "pi":
                    raise ExprError("'pi' is a constant, not a function", start, name)
                if name not in FUNCTIONS:
                    hint = did_you_mean(name, FUNCTIONS)
                    raise ExprError(f"unknown function '{name}'{hint}", start, name)
                toks.append(_Tok("func", name, start))
            elif name == "pi":
                toks.append(_Tok("num", name, start, math.pi))
            else:
                toks.append(_Tok("name", name, start))
        elif text.startswith("**", i):
            toks.append(_Tok("op", "**", i))
            i += 2
        elif ch in "+-*/(),":
            toks.append(_Tok("op", ch, i))
            i += 1
        else:
            raise _char_error(ch, i)
    toks.append(_Tok("end", "", n))
    return toks


# ------------------------------------------------------------------------------- parser

#: Infix operator -> (left binding power, binding power of its right operand).
_INFIX = {"+": (10, 10), "-": (10, 10), "*": (20, 20), "/": (20, 20), "**": (40, 39)}
_UNARY_BP = 30  # the operand of a unary sign may contain ** but not * / + -


class _Parser:
    """Pratt parser over a token list; methods return (node, AST height, start column)."""

    def __init__(self, toks: list[_Tok]) -> None:
        self.toks = toks
        self.pos = 0

    def next(self) -> _Tok:
        tok = self.toks[self.pos]
        self.pos += 1
        return tok

    def peek(self) -> _Tok:
        return self.toks[self.pos]

    def unexpected(self, tok: _Tok) -> ExprError:
        if tok.kind == "end":
            return ExprError("unexpected end of expression", tok.col)
        at = next(i for i, t in enumerate(self.toks) if t is tok)
        before = self.toks[at - 1] if at > 0 else None
        if before is not None and before.kind == "num" and before.text != "pi" \
                and tok.kind == "name":
            # a quantity written with its unit (25*t/(400 s)): expressions have no units
            return ExprError(
                f"'{before.text} {tok.text}' at column {before.col + 1}: a number cannot "
                "carry a unit inside an expression; declare the quantity under constants "
                f"with its unit (NAME: {{value: {before.text}, unit: {tok.text}}}) and write "
                f"NAME here (to multiply, write {before.text}*{tok.text})", before.col)
        return ExprError(f"unexpected '{tok.text}' at column {tok.col + 1}", tok.col)

    def expect(self, text: str) -> None:
        tok = self.next()
        if tok.text != text:
            raise self.unexpected(tok)

    @staticmethod
    def check_depth(level: int, col: int) -> None:
        if level > MAX_DEPTH:
            raise ExprError(f"expression is nested too deeply (more than {MAX_DEPTH} levels)", col)

    def expr(self, min_bp: int, depth: int) -> tuple[Node, int, int]:
        """Parse operators binding tighter than min_bp; return (node, height, start column)."""
        self.check_depth(depth, self.peek().col)
        node, height, start = self.prefix(depth)
        while True:
            tok = self.peek()
            if tok.kind != "op" or tok.text not in _INFIX or _INFIX[tok.text][0] <= min_bp:
                return node, height, start
            self.next()
            right, rheight, _ = self.expr(_INFIX[tok.text][1], depth + 1)
            node = Binary(tok.text, node, right, start)
            height = 1 + max(height, rheight)
            self.check_depth(height, tok.col)

    def prefix(self, depth: int) -> tuple[Node, int, int]:
        tok = self.next()
        if tok.kind == "num":
            return Num(tok.value, tok.col), 0, tok.col
        if tok.kind == "name":
            return Name(tok.text, tok.col), 0, tok.col
        if tok.kind == "func":
            return self.call(tok, depth)
        if tok.kind == "op" and tok.text in "+-":
            operand, height, _ = self.expr(_UNARY_BP, depth + 1)
            if tok.text == "+":
                return operand, height, tok.col
            return Unary("-", operand, tok.col), height + 1, tok.col
        if tok.kind == "op" and tok.text == "(":
            node, height, _ = self.expr(0, depth + 1)
            self.expect(")")
            return node, height, tok.col
        raise self.unexpected(tok)

    def call(self, tok: _Tok, depth: int) -> tuple[Node, int, int]:
        self.expect("(")
        args: list[Node] = []
        height = 0
        while self.peek().text != ")" or args:
            arg, arg_height, _ = self.expr(0, depth + 1)
            args.append(arg)
            height = max(height, arg_height)
            if self.peek().text != ",":
                break
            self.next()
        self.expect(")")
        want = FUNCTIONS[tok.text]
        if len(args) != want:
            noun = "argument" if want == 1 else "arguments"
            raise ExprError(
                f"function '{tok.text}' takes {want} {noun}, got {len(args)}", tok.col, tok.text
            )
        return Call(tok.text, tuple(args), tok.col), height + 1, tok.col


def parse(text: str) -> Node:
    """Parse expression text into an AST.

    Parameters
    ----------
    text
        The expression, at most :data:`MAX_LENGTH` characters.

    Returns
    -------
    Node
        The root of the AST; nodes compare equal regardless of their ``col``.

    Raises
    ------
    ExprError
        For any problem with the text (never another exception, never RecursionError).
    """
    if not isinstance(text, str):
        raise ExprError(f"expected an expression as text, found {type(text).__name__}")
    if len(text) > MAX_LENGTH:
        raise ExprError(f"expression is too long ({len(text)} characters, limit {MAX_LENGTH})")
    if not text.strip():
        raise ExprError("empty expression")
    return _parse(text)


@functools.lru_cache(maxsize=1024)
def _parse(text: str) -> Node:
    """:func:`parse` of checked text, memoised: a text used many times (a YAML alias, a
    model used by several instances) is parsed once; the AST is immutable."""
    parser = _Parser(_tokenize(text))
    node, _, _ = parser.expr(0, 0)
    if parser.peek().kind != "end":
        raise parser.unexpected(parser.peek())
    return node


def names(node: Node) -> list[Name]:
    """List the free symbols of an AST.

    Parameters
    ----------
    node
        The AST.

    Returns
    -------
    list of Name
        Every Name node, repeats included, in order of appearance. ``pi`` is a Num.
    """
    if isinstance(node, Name):
        return [node]
    if isinstance(node, Unary):
        return names(node.operand)
    if isinstance(node, Binary):
        return names(node.left) + names(node.right)
    if isinstance(node, Call):
        return [n for arg in node.args for n in names(arg)]
    return []


def size(node: Node) -> int:
    """Number of nodes of an AST (numbers, names, operators and calls)."""
    if isinstance(node, Unary):
        return 1 + size(node.operand)
    if isinstance(node, Binary):
        return 1 + size(node.left) + size(node.right)
    if isinstance(node, Call):
        return 1 + sum(size(arg) for arg in node.args)
    return 1


def total_size(nodes: Iterable[Node]) -> int:
    """Total :func:`size` of ``nodes``, every repeat counted (each distinct AST once
    measured): the work an expanded document asks for."""
    sizes: dict[int, int] = {}
    total = 0
    for node in nodes:
        if id(node) not in sizes:
            sizes[id(node)] = size(node)
        total += sizes[id(node)]
    return total


def rename(node: Node, new_name: Callable[[str], str]) -> Node:
    """Return ``node`` with every Name ``n`` replaced by ``new_name(n)``.

    Parameters
    ----------
    node
        The AST (not modified).
    new_name
        Maps an old symbol name to the new one.
    """
    if isinstance(node, Name):
        return replace(node, name=new_name(node.name))
    if isinstance(node, Unary):
        return replace(node, operand=rename(node.operand, new_name))
    if isinstance(node, Binary):
        return replace(node, left=rename(node.left, new_name),
                       right=rename(node.right, new_name))
    if isinstance(node, Call):
        return replace(node, args=tuple(rename(a, new_name) for a in node.args))
    return node


# ----------------------------------------------------------------------------- backends

_CASADI_FUNCS: dict[str, Callable[..., casadi.SX]] = {
    "sin": casadi.sin, "cos": casadi.cos, "tan": casadi.tan, "asin": casadi.asin,
    "acos": casadi.acos, "atan": casadi.atan, "sqrt": casadi.sqrt, "exp": casadi.exp,
    "log": casadi.log, "abs": casadi.fabs, "sinh": casadi.sinh, "cosh": casadi.cosh,
    "tanh": casadi.tanh, "atan2": casadi.atan2,
}
_CASADI_OPS: dict[str, Callable[[casadi.SX, casadi.SX], casadi.SX]] = {
    "+": operator.add, "-": operator.sub, "*": operator.mul, "/": operator.truediv,
    "**": casadi.power,
}


def to_casadi(node: Node, resolve: Callable[[Name], casadi.SX]) -> casadi.SX:
    """Build the CasADi SX of an AST.

    Parameters
    ----------
    node
        The AST (as returned by :func:`parse`).
    resolve
        Called once per Name occurrence; returns its SX (the caller memoises).

    Returns
    -------
    casadi.SX
        The expression. ``**`` is CasADi's power, ``abs`` is ``fabs``.
    """
    if isinstance(node, Num):
        return casadi.SX(node.value)
    if isinstance(node, Name):
        return resolve(node)
    if isinstance(node, Unary):
        operand = to_casadi(node.operand, resolve)
        return -operand if node.op == "-" else operand
    if isinstance(node, Binary):
        a, b = to_casadi(node.left, resolve), to_casadi(node.right, resolve)
        return _CASADI_OPS[node.op](a, b)
    return _CASADI_FUNCS[node.func](*(to_casadi(arg, resolve) for arg in node.args))


def _ieee(fn: Callable[..., float], *args: float) -> float:
    """Call a math function, mapping its exceptions to the IEEE result C's libm returns."""
    try:
        return fn(*args)
    except OverflowError:
        if fn is math.pow:
            x, y = args
            odd = y == math.floor(y) and math.fmod(y, 2.0) != 0.0
            return -math.inf if x < 0 and odd else math.inf
        return math.copysign(math.inf, args[0]) if fn is math.sinh else math.inf
    except ValueError:
        if fn is math.log and args[0] == 0.0:
            return -math.inf
        if fn is math.pow and args[0] == 0.0 and args[1] < 0:  # pole of x**y at x == 0
            return -math.inf if math.copysign(1.0, args[0]) < 0 and args[1] % 2 == 1 else math.inf
        return math.nan


def _div(a: float, b: float) -> float:
    if b != 0.0:
        return a / b
    if a == 0.0 or math.isnan(a):
        return math.nan
    return math.copysign(math.inf, a) * math.copysign(1.0, b)


_MATH_FUNCS: dict[str, Callable[..., float]] = {
    "sin": math.sin, "cos": math.cos, "tan": math.tan, "asin": math.asin, "acos": math.acos,
    "atan": math.atan, "sqrt": math.sqrt, "exp": math.exp, "log": math.log, "abs": math.fabs,
    "sinh": math.sinh, "cosh": math.cosh, "tanh": math.tanh, "atan2": math.atan2,
}
_MATH_OPS: dict[str, Callable[[float, float], float]] = {
    "+": operator.add, "-": operator.sub, "*": operator.mul, "/": _div,
    "**": lambda a, b: _ieee(math.pow, a, b),
}


def evaluate(node: Node, env: Mapping[str, float]) -> float:
    """Evaluate an AST in pure Python: the reference against which CasADi is tested.

    Arithmetic follows IEEE 754 instead of raising: ``x/0`` is ``±inf`` (``0/0`` is nan),
    overflow (``10**10**10``, ``exp(1000)``) is ``±inf``, poles (``log(0)``, ``0**-1``) are
    ``±inf`` as in C, and other domain errors (``log(-1)``, ``sqrt(-1)``, ``(-8)**(1/3)``,
    ``sin(inf)``) are nan.

    Parameters
    ----------
    node
        The AST.
    env
        Value of every name (dotted names are looked up whole, e.g. ``"s1.p_hat"``).

    Raises
    ------
    ExprError
        If a name is missing from ``env``.
    """
    if isinstance(node, Num):
        return float(node.value)
    if isinstance(node, Name):
        if node.name not in env:
            hint = did_you_mean(node.name, env)
            raise ExprError(f"unknown symbol '{node.name}'{hint}", node.col, node.name)
        return float(env[node.name])
    if isinstance(node, Unary):
        operand = evaluate(node.operand, env)
        return -operand if node.op == "-" else operand
    if isinstance(node, Binary):
        return _MATH_OPS[node.op](evaluate(node.left, env), evaluate(node.right, env))
    args = [evaluate(arg, env) for arg in node.args]
    return float(_ieee(_MATH_FUNCS[node.func], *args))


# ------------------------------------------------------------------------------- render

_PREC = {"+": 1, "-": 1, "*": 2, "/": 2, "**": 4}
_UNARY_PREC, _ATOM_PREC = 3, 5


def _prec(node: Node) -> int:
    if isinstance(node, Binary):
        return _PREC[node.op]
    if isinstance(node, Unary) or (isinstance(node, Num) and math.copysign(1, node.value) < 0):
        return _UNARY_PREC
    return _ATOM_PREC


def _wrap(node: Node, need_parens: bool) -> str:
    text = render(node)
    return f"({text})" if need_parens else text


def render(node: Node) -> str:
    """Render an AST as text with the fewest parentheses that keep its structure.

    ``parse(render(n)) == n`` for every tree :func:`parse` returns. ``Num(math.pi)`` renders
    as ``pi`` and ``Num(inf)`` as ``1e999``; a negative Num renders as a unary minus.

    Raises
    ------
    ValueError
        For a ``Num`` whose value is nan, which has no textual form.
    """
    if isinstance(node, Num):
        value = float(node.value)
        if math.isnan(value):
            raise ValueError("cannot render a nan number")
        if math.copysign(1.0, value) < 0:
            return render(Unary("-", Num(-value)))
        return "pi" if value == math.pi else "1e999" if math.isinf(value) else repr(value)
    if isinstance(node, Name):
        return node.name
    if isinstance(node, Unary):
        return node.op + _wrap(node.operand, _prec(node.operand) < _UNARY_PREC)
    if isinstance(node, Call):
        return f"{node.func}({', '.join(render(arg) for arg in node.args)})"
    prec = _PREC[node.op]
    if node.op == "**":  # right-associative; its right operand may be a unary sign
        left = _wrap(node.left, _prec(node.left) < _ATOM_PREC)
        return f"{left}**{_wrap(node.right, _prec(node.right) < _UNARY_PREC)}"
    left = _wrap(node.left, _prec(node.left) < prec)
    right = _wrap(node.right, _prec(node.right) <= prec)
    return f"{left} {node.op} {right}" if prec == 1 else f"{left}{node.op}{right}"
