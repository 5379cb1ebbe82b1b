"""The fuel-time Pareto front of the cycle: minimum fuel at fixed cycle times, cached on disk.

The sweep runs from the minimum-time cycle to the fuel-optimal one. Every point is warm-started from
its neighbour (continuation) on one mesh fine enough for the longest cycle; near the minimum time,
where the problem has several local optima (other splits of the time between the four phases), template
starts are tried beside it. A second pass continues back from the fuel-optimal end (a forward chain
that took a worse basin carries it along). The best verified solution of each point is kept. Each
solve is re-simulated and written to the cache as soon as it is done, so an interrupted sweep resumes
where it stopped. The cache key is the braking alternative, the parameter fingerprint and the number of
points. :func:`pareto_fronts` sweeps both braking alternatives in parallel processes.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from mpc.benchmark.ocp import (
    OCPError,
    OCPResult,
    OCPSettings,
    solve_ocp,
    write_json_atomic,
)
from wl_env import cycle
from wl_env.params import LoaderParams, resolve

CACHE_ENV = "WL_CACHE_DIR"
FIRST_POINT_SLACK = 1e-3  # the front starts at T_min * (1 + this): minimum fuel in the fastest cycle
# Template starts (leg = T/2, these acceleration fractions) beside the neighbour's warm start, at cycle
# times below MULTI_START_BELOW * T_min. Measured on both alternatives (7 points, templates 0.6/0.7/0.8):
# templates beat continuation by 0.3-1.2 % within 4 % of T_min (0.6 or 0.8 won; 0.7 never alone), never
# from 13 % on.
SWEEP_ACCEL_FRACTIONS = (0.6, 0.8)
MULTI_START_BELOW = 1.10


def cache_dir(path: str | os.PathLike | None = None) -> Path:
    """Where solved optima are kept: ``path``, else $WL_CACHE_DIR, else ~/.cache/wheel-loader-gym."""
    if path is not None:
        return Path(path)
    env = os.environ.get(CACHE_ENV)
    return Path(env) if env else Path.home() / ".cache" / "wheel-loader-gym"


@dataclass
class ParetoFront:
    """Minimum fuel against cycle time for one braking alternative (points sorted by T)."""

    braking: str
    T: list[float]
    fuel_g: list[float]
    params_fingerprint: str
    T_min: float
    T_fuel_opt: float
    fuel_min_g: float
    mesh: list[int]
    wall_time: float = 0.0
    points: list[dict[str, Any]] = field(default_factory=list)  # per point: T, fuel, verification summary

    def fuel_at(self, T: float) -> float:
        """Optimal fuel (g) at cycle time T, interpolated on the front (monotone cubic, T_min <= T < T_fuel_opt).

        Between T_min and the first point (0.1 % above it) the first point's fuel is returned.
        """
        if not math.isfinite(T):
            raise ValueError(f"cycle time must be finite, got {T!r}")
        if T < self.T_min - 1e-6:
            raise ValueError(
                f"cycle time {T:.3f} s is impossible: the minimum cycle time with {self.braking} braking is "
                f"{self.T_min:.3f} s"
            )
        if T >= self.T_fuel_opt:
            raise ValueError(
                f"cycle time {T:.3f} s lies beyond the fuel-optimal cycle ({self.T_fuel_opt:.3f} s); "
                f"use optimal_fuel_at(), which solves such points on demand"
            )
        return float(pchip(np.asarray(self.T), np.asarray(self.fuel_g), max(T, self.T[0])))

    def save(self, path: str | os.PathLike) -> Path:
        return write_json_atomic(path, self.__dict__)

    @classmethod
    def load(cls, path: str | os.PathLike) -> ParetoFront:
        data = json.loads(Path(path).read_text())
        return cls(**{k: v for k, v in data.items() if k in cls.__dataclass_fields__})


def pchip(x: np.ndarray, y: np.ndarray, xq: float) -> float:
    """Monotone piecewise-cubic interpolation (Fritsch-Carlson): follows the convex front between points
    without overshoot, where a straight chord would overstate the optimal fuel."""
    h = np.diff(x)
    delta = np.diff(y) / h
    m = np.zeros_like(y)
    m[0], m[-1] = delta[0], delta[-1]
    for k in range(1, len(x) - 1):
        if delta[k - 1] * delta[k] > 0:
            w1, w2 = 2 * h[k] + h[k - 1], h[k] + 2 * h[k - 1]
            m[k] = (w1 + w2) / (w1 / delta[k - 1] + w2 / delta[k])
    k = int(np.clip(np.searchsorted(x, xq) - 1, 0, len(x) - 2))
    t = (xq - x[k]) / h[k]
    h00, h10, h01, h11 = 2 * t**3 - 3 * t**2 + 1, t**3 - 2 * t**2 + t, -2 * t**3 + 3 * t**2, t**3 - t**2
    return float(h00 * y[k] + h10 * h[k] * m[k] + h01 * y[k + 1] + h11 * h[k] * m[k + 1])


def _key(braking: str, p: LoaderParams, n_points: int) -> str:
    return f"{braking}_{p.fingerprint()}_n{n_points}_v4"


def front_folder(braking: str, n_points: int = 8, params: LoaderParams | dict | None = None,
                 cache: str | os.PathLike | None = None) -> Path:
    """Where :func:`pareto_front` keeps a front: ``front.json``, ``min_time.json``, ``min_fuel.json``
    and one ``T_<cycle time>.json`` per point (each an :class:`mpc.benchmark.ocp.OCPResult`)."""
    return cache_dir(cache) / "pareto" / _key(cycle.check_braking(braking), resolve(params), n_points)


def sweep_mesh(ends: list[OCPResult], max_interval: float) -> tuple[int, int, int, int]:
    """One mesh for the whole sweep (one NLP, built once): no interval longer than ``max_interval`` in
    the longest phase durations of the front's two ends, half that in the braking phases 2 and 4.

    Measured on the service front: with 0.15 s in the braking phases the re-simulated bucket height of
    the 9.2 s cycle missed by 3.6 cm (limit 2 cm); the lift rides the pump limit there while the engine
    speed falls fast, and 0.075 s brings the miss under 1 cm.
    """
    longest = np.max([r.phase_durations for r in ends], axis=0)
    base = np.max([r.mesh for r in ends], axis=0)
    limits = (max_interval, max_interval / 2, max_interval, max_interval / 2)
    return tuple(max(int(b), math.ceil(d / h)) for d, b, h in zip(longest, base, limits, strict=True))  # type: ignore[return-value]


def pareto_front(
    braking: str = "service",
    n_points: int = 8,
    params: LoaderParams | dict | None = None,
    cache: str | os.PathLike | None = None,
    use_cache: bool = True,
    progress: Callable[[str], None] | None = None,
    max_interval: float = 0.15,
) -> ParetoFront:
    """The Pareto front with ``n_points`` cycle times from the minimum time to the fuel optimum.

    Solved points are cached (one JSON per point plus the front); a cached front is returned at once.
    """
    cycle.check_braking(braking)
    if not (isinstance(n_points, int) and 3 <= n_points <= 100):
        raise ValueError(f"n_points must be an integer in [3, 100], got {n_points!r}")
    p = resolve(params)
    say = progress or (lambda msg: None)
    folder = front_folder(braking, n_points, p, cache)
    front_file = folder / "front.json"
    if use_cache and front_file.exists():
        return ParetoFront.load(front_file)
    folder.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()

    def cached_solve(name: str, **kwargs: Any) -> OCPResult:
        path = folder / f"{name}.json"
        if use_cache and path.exists():
            return OCPResult.load(path)
        result = solve_ocp(braking, params=p, **kwargs)
        result.save(path)
        return result

    say(f"[{braking}] minimum time")
    r_time = cached_solve("min_time", objective="time")
    say(f"[{braking}] minimum time {r_time.T:.3f} s, {r_time.fuel_g:.2f} g; minimum fuel")
    r_fuel = cached_solve("min_fuel", objective="fuel")
    say(f"[{braking}] minimum fuel {r_fuel.fuel_g:.2f} g at {r_fuel.T:.3f} s")
    settings = OCPSettings(intervals=sweep_mesh([r_time, r_fuel], max_interval))
    # Points cluster towards the minimum time, where the front bends most. The minimum-time problem
    # leaves the fuel free (its optimum is not unique), so the front's first point is the minimum fuel
    # a hair above the minimum time instead.
    times = r_time.T + (r_fuel.T - r_time.T) * np.linspace(0.0, 1.0, n_points) ** 2
    times[0] = r_time.T * (1.0 + FIRST_POINT_SLACK)
    points: list[OCPResult] = []
    previous = r_time
    for i, T in enumerate(times[:-1]):
        say(f"[{braking}] point {i + 1}/{n_points}: minimum fuel at T = {T:.3f} s")
        # Continuation from the neighbour; near T_min also fresh template starts, which can end in
        # other local optima (other splits of the time between the phases). The best one is kept.
        templates = tuple((T / 2.0, a) for a in SWEEP_ACCEL_FRACTIONS)
        try:
            r = cached_solve(f"T_{T:.4f}", objective="fuel_at_time", T=float(T), settings=settings,
                             warm_start=previous, starts=templates if T < MULTI_START_BELOW * r_time.T else ())
        except OCPError:  # continuation lost the way: start afresh from the templates
            r = cached_solve(f"T_{T:.4f}", objective="fuel_at_time", T=float(T), settings=settings, starts=templates)
        points.append(r)
        previous = r
    points.append(r_fuel)
    # Continuation back from the fuel-optimal end: a forward chain that took a worse basin near T_min
    # carries it along; the neighbour on the long side may lead into a better one.
    for i in range(len(points) - 2, 0, -1):
        T = float(times[i])
        say(f"[{braking}] point {i + 1}/{n_points}: continuation from T = {points[i + 1].T:.3f} s")
        try:
            alt = cached_solve(f"T_{T:.4f}_back", objective="fuel_at_time", T=T, settings=settings,
                               warm_start=points[i + 1], starts=())
        except OCPError:  # the forward point stands
            continue
        if alt.verification.get("passed") and alt.fuel_g < points[i].fuel_g - 1e-6:
            alt.starts = points[i].starts + alt.starts
            points[i] = alt
    fuel = [r.fuel_g for r in points]
    front = ParetoFront(
        braking=braking, T=[float(r.T) for r in points], fuel_g=fuel, params_fingerprint=p.fingerprint(),
        T_min=float(r_time.T),  # the minimum time itself; the first point lies 0.1 % above it
        T_fuel_opt=float(r_fuel.T), fuel_min_g=float(r_fuel.fuel_g), mesh=list(settings.intervals),
        wall_time=time.perf_counter() - t0,
        points=[{"T": r.T, "fuel_g": r.fuel_g, "mesh": r.mesh, "verified": r.verification.get("passed"),
                 "final_position_error_m": r.verification.get("final_position_error_m"),
                 "final_height_error_m": r.verification.get("final_height_error_m"),
                 "max_violation": r.verification.get("max_violation")} for r in points],
    )
    front.save(front_file)
    return front


def _stderr(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def pareto_fronts(
    brakings: tuple[str, ...] = cycle.BRAKING_MODES,
    n_points: int = 8,
    params: LoaderParams | dict | None = None,
    cache: str | os.PathLike | None = None,
    use_cache: bool = True,
    progress: bool = False,
    workers: int | None = None,
) -> dict[str, ParetoFront]:
    """The fronts of several braking alternatives, swept in parallel processes (one per alternative,
    at most ``workers``, default the CPU count). ``progress`` prints each step to stderr.

    The processes are spawned, so they import the caller's main module: a script that calls this needs
    the usual ``if __name__ == "__main__":`` guard (``wl`` and pytest have it).
    """
    for b in brakings:
        cycle.check_braking(b)
    p = resolve(params)
    say = _stderr if progress else None
    workers = min(len(brakings), workers or os.cpu_count() or 1)
    if workers <= 1:
        return {b: pareto_front(b, n_points, p, cache, use_cache, say) for b in brakings}
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    # spawn, not fork: the parent may hold threads (torch, BLAS) that a forked child would inherit locked
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        jobs = {b: pool.submit(pareto_front, b, n_points, p, cache, use_cache, say) for b in brakings}
        return {b: job.result() for b, job in jobs.items()}


def optimal_fuel_at(T: float, braking: str = "service", params: LoaderParams | dict | None = None,
                    cache: str | os.PathLike | None = None, front: ParetoFront | None = None) -> float:
    """Minimum fuel (g) at cycle time T: interpolated on the front, solved on demand past the fuel optimum.

    Raises ``ValueError`` for a cycle time below the minimum.
    """
    front = front or pareto_front(braking, params=params, cache=cache)
    if T < front.T_fuel_opt:
        return front.fuel_at(T)
    # Slower than the fuel-optimal cycle: fuel at that T is its own optimum (cached like the front).
    p = resolve(params)
    path = cache_dir(cache) / "pareto" / f"slow_{braking}_{p.fingerprint()}" / f"T_{T:.3f}.json"
    if path.exists():
        return OCPResult.load(path).fuel_g
    r = solve_ocp(braking, objective="fuel_at_time", T=float(T), params=p,
                  settings=replace(OCPSettings(), intervals=tuple(front.mesh)))
    r.save(path)
    return r.fuel_g
