"""A suite's reference optima (``wl suite solve``): per scenario, T_min and the Pareto front, re-simulated.

The scenarios of each braking alternative are ordered as a nearest-neighbour chain from the nominal
cycle, so that each front is warm-started from the one solved just before it (``pareto_front``'s
``neighbour``), and the chains are split between the workers: local processes by default
(:mod:`mpc.workers`: Ctrl-C stops them within about a second), or Ray tasks on a cluster
(``ray_address``; ``"local"`` starts a Ray instance on this machine). Each scenario's result is written
atomically to ``<cache>/suites/<suite>/<braking>_<fingerprint>.json`` as soon as it is solved; a killed
sweep resumes with the scenarios that have none. The suite's file (every entry, checked) is assembled
at the end: ``wl suite solve --suite test --out mpc/benchmark/references/test.json`` is how the shipped
optima were made.
"""

from __future__ import annotations

import logging
import math
import os
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mpc.benchmark import store
from mpc.benchmark.ocp import scenario_fields
from mpc.benchmark.pareto import (
    CACHE_VERSION,
    DEFAULT_POINTS,
    FRONT_KIND,
    ParetoFront,
    cache_dir,
    check_front_points,
    check_n_points,
    pareto_front,
)
from mpc.benchmark.reference import SUITE_KIND, check_suite_file, shipped_fronts
from wl_env.cycle import BRAKING_MODES
from wl_env.params import is_integer, shown
from wl_env.scenario import Scenario, param_distance
from wl_env.suites import load_suite

log = logging.getLogger(__name__)

CHECK_TOL = {"T_min": 1e-3, "fuel": 3e-3}  # --check: relative agreement of a fresh solve with the shipped optimum
JOB = f"{__name__}:solve_one"  # the per-scenario solve (module:function, so that a worker or a Ray task imports it)


@dataclass
class SuiteSolve:
    """What a suite solve did: per scenario key its entry, and the times."""

    suite: str
    entries: dict[str, dict[str, Any]]
    solved: int  # solved now (the rest came from earlier runs)
    wall_time: float
    failed: dict[str, str] = field(default_factory=dict)  # scenario key -> the solver's message
    per_scenario_s: list[float] = field(default_factory=list)  # each solved front's own wall time
    file: Path | None = None


def entry_key(scenario: Scenario) -> str:
    return f"{scenario.braking}_{scenario.params().fingerprint()}"


def chain_order(scenarios: list[Scenario]) -> list[Scenario]:
    """A nearest-neighbour chain through the scenarios (:func:`wl_env.scenario.param_distance`, as
    ``pareto.nearest_front`` finds a warm start), from the one nearest the nominal cycle."""
    left = list(scenarios)
    if not left:
        return []
    fields = {s: scenario_fields(s.params()) for s in [*left, Scenario.nominal(left[0].braking)]}
    order = [Scenario.nominal(left[0].braking)]
    while left:
        nxt = min(left, key=lambda s: param_distance(fields[s], fields[order[-1]]))
        order.append(nxt)
        left.remove(nxt)
    return order[1:]


def check_entry(d: dict[str, Any], n_points: int) -> str | None:
    """What is wrong with a scenario's entry in a suite's ``..._n<n_points>_...`` folder: a front of ``n_points``
    point records (:func:`check_front_points`; another count was taken as that folder's) with its scenario."""
    problem = check_front_points(d, n_points)
    if problem is None and not isinstance(d.get("scenario"), dict):
        problem = "missing its scenario"
    return problem


def solve_one(scenario: Scenario, cache: str | os.PathLike | None, n_points: int = DEFAULT_POINTS) -> dict[str, Any]:
    """One scenario's entry: its front (warm-started from the nearest front in ``cache``) and its scenario."""
    t0 = time.perf_counter()
    front = pareto_front(scenario=scenario, n_points=n_points, cache=cache, progress=log.debug)
    return {**front.__dict__, "scenario": scenario.to_dict(), "solve_s": time.perf_counter() - t0}


def _job(job: Any) -> Any:
    """The function ``job`` (``module:function``) names; ValueError naming it if it names none (a bad name was a
    ModuleNotFoundError, AttributeError or TypeError inside the workers, after the cache's folder was made)."""
    import pkgutil

    if not (isinstance(job, str) and job.count(":") == 1 and all(job.split(":"))):
        raise ValueError(f"job must name a function as 'module:function', got {shown(job)}")
    try:
        fn = pkgutil.resolve_name(job)
    except (Exception, SystemExit) as exc:  # (an import runs the module's code: whatever it raises, named)
        raise ValueError(f"job {job!r} names no function: {type(exc).__name__}: {exc}") from None
    if not callable(fn):
        raise ValueError(f"job {job!r} is no function (a {type(fn).__name__})")
    return fn


def _solve_chain(scenarios: list[dict[str, Any]], folder: str, cache: str | None, n_points: int,
                 job: str = JOB) -> dict[str, str]:
    """A worker's chain: each scenario solved in turn and written to ``folder`` at once (atomically). Returns
    the scenarios no solve could do, with the solver's message (the chain goes on without them)."""
    from mpc.benchmark.ocp import OCPError

    failed = {}
    solve = _job(job)
    for d in scenarios:
        s = Scenario.from_dict(d)
        try:
            e = solve(s, cache, n_points)
        except OCPError as exc:
            log.warning(f"{s.label()}: no front ({exc})")
            failed[entry_key(s)] = str(exc)
            continue
        store.write_entry(Path(folder) / f"{entry_key(s)}.json", FRONT_KIND, e, lambda d: check_entry(d, n_points))
    return failed


def _split(chains: dict[str, list[Scenario]], parts: int) -> list[list[Scenario]]:
    """``parts`` pieces of work: each braking alternative's chain cut into consecutive pieces (fewer workers
    than alternatives: the chains one after the other)."""
    if parts < len(chains):
        return [[s for chain in chains.values() for s in chain]]
    per = parts // len(chains)
    out = []
    for chain in chains.values():
        n = math.ceil(len(chain) / per)
        out += [chain[i:i + n] for i in range(0, len(chain), n)]
    return [c for c in out if c]


def solve_suite(suite: str, cache: str | os.PathLike | None = None, out: str | os.PathLike | None = None,
                workers: int | None = None, ray_address: str | None = None, n_points: int = DEFAULT_POINTS,
                limit: int | None = None, ray_chunk: int = 4, job: str = JOB) -> SuiteSolve:
    """Solve (or resume) every scenario of a list suite and assemble its file (``out``, default
    ``<cache>/suites/<suite>.json``). ``limit``: only the first scenarios of each braking alternative's chain.
    ``job``: the per-scenario solve as ``module:function(scenario, cache, n_points) -> entry`` (default
    :func:`solve_one`)."""
    # (limit 0 or -1 wrote a suite file without the scenarios, 2.5 was a TypeError from a slice; a bad n_points
    # failed in the workers, ray_chunk 0 in range())
    if not (limit is None or (is_integer(limit) and limit >= 1)):
        raise ValueError(f"limit must be None or an integer >= 1 (scenarios per braking alternative), got {shown(limit)}")
    n_points = check_n_points(n_points)
    if not (is_integer(ray_chunk) and ray_chunk >= 1):
        raise ValueError(f"ray_chunk must be an integer >= 1 (scenarios per Ray task), got {shown(ray_chunk)}")
    limit, ray_chunk = None if limit is None else int(limit), int(ray_chunk)
    _job(job)  # (resolved here too: a bad name failed only inside the workers)
    s = load_suite(suite)
    if s.sampler:
        raise ValueError(f"suite {suite!r} is a sampler, not a list: it has no fixed optima to solve")
    if workers is not None:
        from mpc.workers import check_workers

        check_workers(workers)
    # the suite's file, checked before any solve (a folder or device there, or an `out` that is no path, failed only
    # once every scenario was solved: hours of work, then a ValueError or a TypeError)
    from wl_env.atomic_io import check_output_file, folders_kept_if_used

    if out is not None and not isinstance(out, (str, os.PathLike)):
        raise ValueError(f"out must be a file path or None, got {shown(out)}")
    target = out if out is not None else cache_dir(cache) / "suites" / f"{suite}.json"
    # (the folders it makes, removed again if it stops and leaves them empty: Ctrl-C before the first entry left
    # <cache>/suites/ and the suite's folder empty; that folder is made by its first entry's write)
    with folders_kept_if_used(Path(target).parent):
        path = check_output_file(target, "out")
        root = cache_dir(cache)  # (a file in the entries' folder's place failed each worker after its first front)
        folder = store.entry_folder(root / "suites" / f"{suite}_v{s.version}_n{n_points}_{CACHE_VERSION}", root)
        chains = {b: chain_order(list(s.of(b)))[:limit] for b in BRAKING_MODES if s.of(b)}
        wanted = [sc for chain in chains.values() for sc in chain]
        def load(sc: Scenario, read: Any) -> Any:  # (the entry's name alone does not vouch for its cycle: both checked)
            return read(folder / f"{entry_key(sc)}.json", FRONT_KIND, lambda d: check_entry(d, n_points),
                        sc.params().fingerprint(), {"braking": sc.braking})

        have = {entry_key(sc) for sc in wanted if load(sc, store.load_entry) is not None}
        todo = {b: [sc for sc in chain if entry_key(sc) not in have] for b, chain in chains.items()}
        todo = {b: c for b, c in todo.items() if c}
        n_todo = sum(map(len, todo.values()))
        log.info(f"suite {suite}: {len(wanted)} scenarios, {len(have)} already solved, {n_todo} to solve in {folder}")
        t0 = time.perf_counter()
        failed: dict[str, str] = {}
        if todo and ray_address is not None:
            failed = _run_on_ray(todo, folder, cache, n_points, ray_address, ray_chunk, job)
        elif todo:
            pieces = _split(todo, workers or os.cpu_count() or 1)
            args = (None if cache is None else str(cache), n_points, job)
            if len(pieces) == 1:
                failed = _solve_chain([sc.to_dict() for sc in pieces[0]], str(folder), *args)
            else:
                from mpc.workers import run_in_workers

                done = run_in_workers({f"chain{i}": (f"{__name__}:_solve_chain", ([sc.to_dict() for sc in p], str(folder),
                                                                                   *args)) for i, p in enumerate(pieces)})
                failed = {k: v for f in done.values() for k, v in f.items()}
        wall = time.perf_counter() - t0
        entries = {entry_key(sc): load(sc, store.read_entry) for sc in wanted if entry_key(sc) not in failed}
        for e in entries.values():
            for k in ("schema", "checksum"):
                e.pop(k, None)
        data = {"suite": suite, "suite_version": s.version, "cache_version": CACHE_VERSION, "n_points": n_points,
                "entries": entries}
        store.write_entry(path, SUITE_KIND, data, check_suite_file)
        solved_now = [e["solve_s"] for k, e in entries.items() if k not in have]
        return SuiteSolve(suite=suite, entries=entries, solved=n_todo - len(failed), wall_time=wall,
                          per_scenario_s=solved_now, file=path, failed=failed)


def _run_on_ray(todo: dict[str, list[Scenario]], folder: Path, cache: str | os.PathLike | None, n_points: int,
                address: str, chunk: int, job: str = JOB) -> dict[str, str]:
    """The chains as Ray tasks of ``chunk`` scenarios each; the driver writes each task's entries as it ends.
    Returns the scenarios no solve could do."""
    from mpc.workers import ray_session

    with ray_session(address) as ray:
        task = ray.remote(_ray_chain)
        pieces = [chain[i:i + chunk] for chain in todo.values() for i in range(0, len(chain), chunk)]
        pending = [task.remote([sc.to_dict() for sc in p], None if cache is None else str(cache), n_points, job)
                   for p in pieces]
        failed: dict[str, str] = {}
        try:
            while pending:
                ready, pending = ray.wait(pending, num_returns=1)
                for key, e in ray.get(ready[0]):
                    if isinstance(e, str):
                        failed[key] = e
                    else:
                        store.write_entry(folder / f"{key}.json", FRONT_KIND, e, lambda d: check_entry(d, n_points))
        except KeyboardInterrupt:
            for ref in pending:
                ray.cancel(ref, force=True)
            raise
        return failed


def _ray_chain(scenarios: list[dict[str, Any]], cache: str | None, n_points: int,
               job: str = JOB) -> list[tuple[str, dict[str, Any]]]:
    """A Ray task: a chain solved in the given cache (a shared folder) or a private temporary one."""
    from mpc.benchmark.ocp import OCPError

    solve = _job(job)
    with tempfile.TemporaryDirectory(prefix="wl-ray-") as tmp:
        out: list[tuple[str, Any]] = []
        for d in scenarios:
            s = Scenario.from_dict(d)
            try:
                out.append((entry_key(s), solve(s, cache or tmp, n_points)))
            except OCPError as exc:  # (a str: the solver's message)
                out.append((entry_key(s), str(exc)))
        return out


def check_shipped(suite: str, cache: str | os.PathLike | None = None, limit: int | None = None,
                  workers: int | None = None, ray_address: str | None = None) -> list[dict[str, Any]]:
    """Solve the suite afresh (in ``cache``) and compare with the shipped optima: one row per scenario with
    the relative differences (fresh / shipped - 1) of T_min and of the fuel at the shipped points (its least and
    largest), and ``ok``: no fresh solve beats the shipped optimum by more than CHECK_TOL. (A shipped optimum is
    a verified cycle; a fresh solve above it found another local optimum: stop 66's re-solved fronts lie 0.15 %
    under the T_min a solve from another chain finds on one `test` cycle.)"""
    if cache is None:  # a fresh solve in a folder of its own, removed after (also on Ctrl-C): nothing cached to reuse
        with tempfile.TemporaryDirectory(prefix="wl-check-") as tmp:
            return check_shipped(suite, tmp, limit, workers, ray_address)
    shipped = shipped_fronts()
    fresh = solve_suite(suite, cache=cache, workers=workers, ray_address=ray_address, limit=limit)
    rows = []
    for key, e in fresh.entries.items():
        old = shipped.get(key)
        if old is None:
            rows.append({"key": key, "ok": False, "problem": "not shipped"})
            continue
        new = ParetoFront._from(e)
        dT = new.T_min / old.T_min - 1.0
        dfuel = [new.fuel_at(T) / f - 1.0 for T, f in zip(old.T, old.fuel_g, strict=True) if new.T[0] <= T < new.T_fuel_opt]
        leaner = min(dfuel, default=0.0)  # (the most a fresh solve beats the shipped front by: negative)
        rows.append({"key": key, "T_min_rel": dT, "fuel_rel_min": leaner, "fuel_rel_max": max(dfuel, default=0.0),
                     "ok": dT >= -CHECK_TOL["T_min"] and leaner >= -CHECK_TOL["fuel"]})
    # a scenario no fresh solve could do is no agreement: it was left out, and `wl suite solve --check` said "3 of 3
    # shipped optima agree" of a 4-scenario check with exit 0
    rows += [{"key": key, "ok": False, "problem": f"no fresh optimum: {why}"} for key, why in fresh.failed.items()]
    return rows
