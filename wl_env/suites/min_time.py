"""An estimate of a scenario's minimum cycle time T_min (s), from its features, without solving an OCP.

A target cycle time is given relative to the scenario's T_min (a policy conditioned on the trade-off sees
target / T_min; training draws targets from T_min to ~2.5 T_min), and a training scenario is a fresh
draw of the ``train`` sampler with no solved optimum: the environment needs T_min at reset, in
microseconds. ``min_time_model.json`` beside this module holds, per braking alternative, a least-squares
fit of T_min over the quadratic terms of the seven scenario features (:meth:`Scenario.features`), on the
minimum-time OCPs of ``train`` draws (``scripts/fit_min_time.py`` writes it, with its provenance and its
measured error). Scoring never uses it: a score's T_min is the cycle's own optimum
(:mod:`mpc.benchmark.reference`).
"""

from __future__ import annotations

import json
import math
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np

from wl_env.cycle import BRAKING_MODES
from wl_env.scenario import Scenario

MODEL_FILE = Path(__file__).resolve().parent / "min_time_model.json"
N_FEATURES = 7


def quadratic_terms(features: Any) -> np.ndarray:
    """[1, f_i, f_i f_j (i <= j)] of feature rows (n, 7) -> (n, 36): the model's regressors."""
    f = np.atleast_2d(np.asarray(features, dtype=float))
    if f.shape[1] != N_FEATURES:
        raise ValueError(f"features must have {N_FEATURES} columns, got shape {f.shape}")
    i, j = np.triu_indices(N_FEATURES)
    return np.hstack([np.ones((len(f), 1)), f, f[:, i] * f[:, j]])


@cache
def _model() -> dict[str, np.ndarray]:
    """The fit's coefficients per braking alternative, read and checked once."""
    try:
        data = json.loads(MODEL_FILE.read_text())
        coef = {b: np.asarray(data["braking"][b]["coefficients"], dtype=float) for b in BRAKING_MODES}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise RuntimeError(f"{MODEL_FILE} is missing or malformed ({exc}): run scripts/fit_min_time.py") from exc
    n_terms = quadratic_terms(np.zeros(N_FEATURES)).shape[1]
    for b, c in coef.items():
        if c.shape != (n_terms,) or not np.isfinite(c).all():
            raise RuntimeError(f"{MODEL_FILE}: the {b} coefficients must be {n_terms} finite numbers")
    return coef


def estimate_min_time(scenario: Scenario) -> float:
    """The estimated minimum cycle time (s) of a scenario (its braking alternative's fit)."""
    if not isinstance(scenario, Scenario):
        raise ValueError(f"scenario must be a wl_env.scenario.Scenario (Scenario.parse reads one from JSON), got "
                         f"{type(scenario).__name__}")
    c = _model()[scenario.braking]
    T = float((quadratic_terms(scenario.features()) @ c)[0])
    if not (math.isfinite(T) and T > 0):
        raise RuntimeError(f"the T_min model gives {T!r} s for {scenario.label()}")
    return T
