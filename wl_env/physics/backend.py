"""One set of math primitives for three kinds of numbers.

The physics functions are written once and evaluated on Python floats (the single environment's fast
path), numpy arrays (the vectorized environment, plots) and CasADi symbols (the OCP and the MPC).
They only use + - * /, and the primitives below, picked from the type of the argument. The model
avoids transcendental functions where algebra does (sin(theta2) = (H - G)/r, cos by sqrt), so floats and
numpy arrays give bit-identical results: every operation used is correctly rounded in IEEE 754.
A fourth kind, the recording ``flatten.Sym``, turns the float path into generated straight-line code.
"""

from __future__ import annotations

import math
from types import SimpleNamespace
from typing import Any

import numpy as np

try:  # casadi is a hard dependency of the project, but the simulator does not need it at import
    import casadi as ca

    _CASADI_TYPES: tuple[type, ...] = (ca.SX, ca.MX, ca.DM)
except ImportError:  # pragma: no cover
    ca = None
    _CASADI_TYPES = ()


def _float_where(cond: Any, a: Any, b: Any) -> Any:
    return a if cond else b


def _float_clip(x: float, lo: float, hi: float) -> float:
    return lo if x < lo else (hi if x > hi else x)


FLOAT_OPS = SimpleNamespace(
    name="float",
    sqrt=math.sqrt,
    fmin=min,
    fmax=max,
    where=_float_where,
    clip=_float_clip,
    isnan=math.isnan,
)

def _numpy_clip(x: Any, lo: Any, hi: Any) -> Any:
    return np.minimum(np.maximum(x, lo), hi)  # = np.clip, without its Python layers (4x faster on (N,))


NUMPY_OPS = SimpleNamespace(
    name="numpy",
    sqrt=np.sqrt,
    fmin=np.minimum,
    fmax=np.maximum,
    where=np.where,
    clip=_numpy_clip,
    isnan=np.isnan,
)

if ca is not None:
    CASADI_OPS = SimpleNamespace(
        name="casadi",
        sqrt=ca.sqrt,
        fmin=ca.fmin,
        fmax=ca.fmax,
        where=lambda c, a, b: ca.if_else(c, a, b),
        clip=lambda x, lo, hi: ca.fmin(ca.fmax(x, lo), hi),
        isnan=lambda x: x != x,
    )


class Traced:
    """Base of recording numbers (``flatten.Sym``): ``ops_for`` hands them their class's ``OPS``."""

    __slots__ = ()
    OPS: SimpleNamespace


def ops_for(*values: Any) -> SimpleNamespace:
    """The primitive set for these arguments: CasADi if any is symbolic, numpy if any is an array."""
    if type(values[0]) is float and len(values) == 1:  # the single environment's hot path
        return FLOAT_OPS
    kind = FLOAT_OPS
    for v in values:
        if isinstance(v, _CASADI_TYPES):
            return CASADI_OPS
        if isinstance(v, np.ndarray):
            kind = NUMPY_OPS
        elif isinstance(v, Traced):
            return v.OPS
    return kind


def is_symbolic(value: Any) -> bool:
    return isinstance(value, _CASADI_TYPES)
