"""Straight-line float code generated from the physics functions: the single environment's fast path.

The physics is written once for floats, numpy arrays and CasADi symbols (see ``backend``). On Python
floats most of its cost is interpretation overhead, not arithmetic: nested function calls, ``ops_for``
dispatch, attribute and dict look-ups of parameters. :func:`flatten` runs a function once on recording
symbols (:class:`Sym`, a fourth kind of number for ``ops_for``) and compiles the recorded operations into
one Python function of plain float arithmetic. Parameters become literals, the float primitives of
``backend.FLOAT_OPS`` are written out inline with the same semantics (``min(a, b)`` is
``b if b < a else a``), and every operation keeps its operands and their order. The generated function
therefore returns bit-identical results to the original called on floats, two to three times faster.
(An operation that occurs twice on the same operands is computed once, and a value used once is
computed inside the expression that uses it: neither changes a result, float arithmetic being
deterministic and never kept in extended precision by Python.)

Straight-line code flattens as it is (the physics uses ``ops.where``, which evaluates both branches, as
numpy and CasADi need anyway). A Python ``if`` on a traced value raises ``TypeError`` at trace time,
unless ``speculate`` is True or False: then the trace follows that branch of every such ``if`` and the
generated code checks it (a guard), returning ``None`` where a value takes the other branch, so that the
caller runs the original code. The cycle's step is flattened twice this way: for substeps that run
through, and for the substep that is cut where the vehicle speed crosses zero.
"""

from __future__ import annotations

import dataclasses
import itertools
import linecache
import math
from collections.abc import Callable
from typing import Any

import numpy as np

from wl_env.physics.backend import FLOAT_OPS, Traced

_serial = itertools.count()  # tells the generated sources apart in tracebacks
_MAX_NESTING = 40  # inlined expressions deeper than this are stored (Python's parser has a depth limit)


class _Tape:
    """The recorded program: operations ``(target, format, operands, lazy operand indices)``."""

    def __init__(self, speculate: bool | None) -> None:
        self.speculate = speculate
        self.ops: list[tuple[str | None, str, tuple[str, ...], tuple[int, ...]]] = []
        self.namespace: dict[str, Any] = {"_sqrt": math.sqrt}
        self._bound: dict[int, str] = {}
        self._known: dict[tuple, Sym] = {}

    def emit(self, fmt: str, *operands: Any, lazy: tuple[int, ...] = ()) -> Sym:
        """A new value ``fmt.format(*operands)``; ``lazy`` operands are evaluated in one branch only."""
        args = tuple(self.ref(v) for v in operands)
        key = (fmt, args)
        if key not in self._known:  # the same operation on the same operands: computed once
            self._known[key] = Sym(self, f"_t{len(self.ops)}")
            self.ops.append((self._known[key].name, fmt, args, lazy))
        return self._known[key]

    def guard(self, cond: Sym) -> None:
        fmt = "if not ({0}): return None" if self.speculate else "if {0}: return None"
        self.ops.append((None, fmt, (cond.name,), ()))

    def ref(self, value: Any) -> str:
        """Source text of an operand: a symbol's name, a literal, or a bound constant."""
        if isinstance(value, Sym):
            return value.name
        if type(value) in (int, bool) or (type(value) is float and math.isfinite(value)):
            text = repr(value)  # round-trips exactly
            return f"({text})" if text.startswith("-") else text
        if id(value) not in self._bound:  # nan, inf, tables, numpy scalars, ...: keep the object itself
            self._bound[id(value)] = name = f"_k{len(self._bound)}"
            self.namespace[name] = value
        return self._bound[id(value)]

    def source(self, returned: set[str]) -> list[str]:
        """The body's lines, values used once (and not in a lazy branch) inlined where they are used;
        operations whose values reach neither the result nor a guard are left out."""
        live = set(returned)
        kept = []
        for op in reversed(self.ops):  # backwards: an operation is live if a live one (or a guard) uses it
            target, _, args, _ = op
            if target is None or target in live:
                live.update(args)
                kept.append(op)
        ops = kept[::-1]
        uses = dict.fromkeys(returned, 2)  # returned values stay variables
        for _, fmt, args, lazy in ops:
            for i, a in enumerate(args):
                weight = 2 if i in lazy else fmt.count(f"{{{i}}}")  # lazy: never inline
                uses[a] = uses.get(a, 0) + weight
        pending: dict[str, tuple[str, int]] = {}  # inlinable name -> (expression, nesting depth)
        lines = []
        for target, fmt, args, _ in ops:
            depth = 1 + max((pending[a][1] for a in args if a in pending), default=0)
            text = fmt.format(*(f"({pending.pop(a)[0]})" if a in pending else a for a in args))
            if target is not None and uses.get(target) == 1 and depth < _MAX_NESTING:
                pending[target] = (text, depth)
            else:
                lines.append(text if target is None else f"{target} = {text}")
        return lines


def _tape_of(*values: Any) -> _Tape:
    return next(v.tape for v in values if isinstance(v, Sym))


def _binary(op: str) -> tuple[Callable, Callable]:
    def forward(a: Sym, b: Any) -> Sym:
        return a.tape.emit(f"{{0}} {op} {{1}}", a, b)

    def reflected(a: Sym, b: Any) -> Sym:  # b <op> a with b not a symbol: keep the operand order
        return a.tape.emit(f"{{0}} {op} {{1}}", b, a)

    return forward, reflected


class Sym(Traced):
    """A recording float: every operation on it appends one operation to its tape."""

    __slots__ = ("tape", "name")

    def __init__(self, tape: _Tape, name: str) -> None:
        self.tape = tape
        self.name = name

    __add__, __radd__ = _binary("+")
    __sub__, __rsub__ = _binary("-")
    __mul__, __rmul__ = _binary("*")
    __truediv__, __rtruediv__ = _binary("/")
    __and__, __rand__ = _binary("&")
    __or__, __ror__ = _binary("|")
    __lt__, __gt__ = _binary("<")[0], _binary(">")[0]  # (a < b reflects to b > a: Python does that)
    __le__, __ge__ = _binary("<=")[0], _binary(">=")[0]
    __eq__, __ne__ = _binary("==")[0], _binary("!=")[0]  # type: ignore[assignment]
    __hash__ = None  # type: ignore[assignment]

    def __neg__(self) -> Sym:
        return self.tape.emit("-{0}", self)

    def __invert__(self) -> Sym:
        return self.tape.emit("~{0}", self)

    def __abs__(self) -> Sym:
        return self.tape.emit("abs({0})", self)

    def __bool__(self) -> bool:
        if self.tape.speculate is None:
            raise TypeError("a Python branch on a traced value cannot be flattened; use ops.where")
        self.tape.guard(self)  # the trace takes the speculated branch; the generated code checks it
        return self.tape.speculate


def take(table: tuple, index: Sym) -> Sym:
    """``table[index]`` looked up at run time (e.g. the gear of a traced phase number)."""
    return index.tape.emit("{0}[{1}]", table, index)


def _sqrt(x: Any) -> Any:
    return x.tape.emit("_sqrt({0})", x) if isinstance(x, Sym) else math.sqrt(x)


def _fmin(a: Any, b: Any) -> Any:  # builtin min(a, b): b only if b < a
    if not (isinstance(a, Sym) or isinstance(b, Sym)):
        return min(a, b)
    return _tape_of(a, b).emit("{1} if {1} < {0} else {0}", a, b, lazy=(0, 1))


def _fmax(a: Any, b: Any) -> Any:  # builtin max(a, b): b only if b > a
    if not (isinstance(a, Sym) or isinstance(b, Sym)):
        return max(a, b)
    return _tape_of(a, b).emit("{1} if {1} > {0} else {0}", a, b, lazy=(0, 1))


def _where(cond: Any, a: Any, b: Any) -> Any:
    if not isinstance(cond, Sym):
        return FLOAT_OPS.where(cond, a, b)
    return cond.tape.emit("{1} if {0} else {2}", cond, a, b, lazy=(1, 2))


def _clip(x: Any, lo: Any, hi: Any) -> Any:
    if not (isinstance(x, Sym) or isinstance(lo, Sym) or isinstance(hi, Sym)):
        return FLOAT_OPS.clip(x, lo, hi)
    return _tape_of(x, lo, hi).emit("{1} if {0} < {1} else ({2} if {0} > {2} else {0})", x, lo, hi, lazy=(0, 1, 2))


def _isnan(x: Any) -> Any:
    return x.tape.emit("{0} != {0}", x) if isinstance(x, Sym) else math.isnan(x)


Sym.OPS = type(FLOAT_OPS)(name="trace", sqrt=_sqrt, fmin=_fmin, fmax=_fmax, where=_where, clip=_clip, isnan=_isnan)


class Flattened:
    """Base of objects that keep flattened code of their own methods in ``_flat``: the code bakes in the
    attributes' values, so assigning any attribute (e.g. a reward curriculum replacing ``reward``)
    discards it, and it is rebuilt after unpickling rather than pickled."""

    _flat: Any = None

    def __setattr__(self, name: str, value: Any) -> None:
        object.__setattr__(self, name, value)
        object.__setattr__(self, "_flat", None)

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "_flat": None}


def config_key(obj: Any) -> str:
    """A key for everything an object's traced methods can read: its type and, recursively, the values of
    its attributes (``_flat``, the generated code itself, apart). Derived, not listed by hand, so an
    attribute added to a step cannot share stale code between two configurations."""

    def walk(v: Any) -> Any:
        if dataclasses.is_dataclass(v) and not isinstance(v, type):
            return repr(v)
        if isinstance(v, np.ndarray):
            return ("ndarray", str(v.dtype), v.shape, repr(v.tolist()))
        if isinstance(v, (tuple, list)):
            return (type(v).__name__, *map(walk, v))
        if isinstance(v, dict):
            return ("dict", *((repr(k), walk(x)) for k, x in v.items()))
        if hasattr(v, "__dict__") and not callable(v):
            return (type(v).__qualname__, *((k, walk(x)) for k, x in sorted(vars(v).items())
                                            if k not in ("_flat", "_steps_unflattened")))
        return repr(v)  # numbers (repr tells -0.0 from 0.0, which == does not), strings, None

    return repr(walk(obj))


_CACHE: dict[str, Callable] = {}
CACHE_SIZE = 64  # flattened functions kept for reuse (each new configuration adds one; oldest go first)


def flatten_cached(key: str, fn: Callable, *inputs: str | tuple[str, int], **options: Any) -> Callable:
    """:func:`flatten`, shared between equal configurations: ``key`` must identify everything the trace
    of ``fn`` reads (:func:`config_key` of the object whose method ``fn`` is)."""
    if key not in _CACHE:
        if len(_CACHE) >= CACHE_SIZE:
            del _CACHE[next(iter(_CACHE))]
        _CACHE[key] = flatten(fn, *inputs, **options)
    return _CACHE[key]


def flatten(fn: Callable, *inputs: str | tuple[str, int], name: str = "flat", speculate: bool | None = None) -> Callable:
    """Compile ``fn`` for floats into straight-line code with the same results.

    ``inputs`` describe fn's positional arguments: a name (one number) or ``(name, n)`` (a sequence of
    which items 0..n-1 are used). The result takes the same arguments; tuples, lists and dicts in fn's
    return value keep their structure. With ``speculate`` (the branch every Python ``if`` on a traced value
takes) it returns ``None`` where a guard fails (see the
    module doc). The generated source is in the function's ``__source__``.
    """
    tape = _Tape(speculate)
    args, signature, prologue = [], [], []
    for spec in inputs:
        if isinstance(spec, str):
            args.append(Sym(tape, spec))
            signature.append(spec)
        else:
            seq, n = spec
            items = [Sym(tape, f"{seq}_{i}") for i in range(n)]
            args.append(tuple(items))
            signature.append(seq)
            prologue += [f"{s.name} = {seq}[{i}]" for i, s in enumerate(items)]
    result = fn(*args)

    returned: set[str] = set()

    def render(value: Any) -> str:
        if isinstance(value, tuple):
            return "(" + "".join(render(v) + ", " for v in value) + ")"
        if isinstance(value, list):
            return "[" + ", ".join(render(v) for v in value) + "]"
        if isinstance(value, dict):
            return "{" + ", ".join(f"{k!r}: {render(v)}" for k, v in value.items()) + "}"
        returned.add(tape.ref(value))
        return tape.ref(value)

    ret = f"return {render(result)}"
    body = prologue + tape.source(returned) + [ret]
    source = f"def {name}({', '.join(signature)}):\n" + "".join(f"    {line}\n" for line in body)
    filename = f"<flattened {getattr(fn, '__qualname__', name)} #{next(_serial)}>"
    linecache.cache[filename] = (len(source), None, source.splitlines(True), filename)  # readable tracebacks
    exec(compile(source, filename, "exec"), tape.namespace)
    flat = tape.namespace[name]
    flat.__source__ = source
    return flat
