"""The main job: solve the benchmark, run every controller on both braking alternatives, write the report.

``wl run`` (the README's first command) calls :func:`run_all` = :func:`collect` + :func:`render`; it writes
into ``results/``: ``results.json`` (everything the report is drawn from: the rows, the Pareto fronts,
the time-optimal cycles and each controller's trajectory), ``leaderboard.md`` (controller, braking,
cycle time, fuel, time gap, fuel gap, violation, success), ``pareto.png`` (the fronts with every
controller's point) and ``trajectories_<braking>.png`` (each controller's states beside the time-optimal
ones). Optima are cached. ``wl report`` calls :func:`load_results` + :func:`render`: the report again from
``results.json``, without solving or running anything. Every file is written atomically
(:mod:`wl_env.atomic_io`): a kill leaves the previous file or the new one, never a part of one.
"""

from __future__ import annotations

import functools
import json
import logging
import os
import re
import shutil
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from wl_env.atomic_io import check_output_file, read_regular_file, save_figure, write_atomic
from wl_env.params import is_real_number

log = logging.getLogger(__name__)

BRAKINGS = ("service", "tc")
RESULTS_FILE = "results.json"
RESULTS_FORMAT = 3  # 1: rows only (cannot be re-rendered); 2: + fronts, optima, trajectories; 3: + the suite
KEEP_DIR = ".evaluations"  # in `wl run`'s --out: each finished controller evaluation until results.json is written
SUITE = "test"  # the suite leaderboard's suite (its optima are shipped: nothing is solved for it)
SUITE_SAMPLE = 10  # scenarios per braking alternative the main job runs by default (--full-suite: all)
ROW_KEYS = ("controller", "braking", "T", "fuel_g", "time_gap", "fuel_gap", "max_violation", "success")


def controllers(braking: str) -> list[tuple[str, Callable[[], Any]]]:
    """(name, factory) of the controllers the report compares; PPO only where a policy is shipped."""
    from agents.evaluate import default_policy_path, load_controller
    from mpc.controller.mpc import MPCConfig, MPCController

    out: list[tuple[str, Callable[[], Any]]] = [
        ("operator", lambda: load_controller("operator", braking)),
        ("mpc (min time)", lambda: MPCController(braking, config=MPCConfig(mode="time"))),
        ("mpc (T = 11 s)", lambda: MPCController(braking, config=MPCConfig(mode="target_time", target_time=11.0))),
    ]
    if default_policy_path(braking).exists():
        out.append(("ppo", lambda: load_controller("ppo", braking)))
    return out


def suite_controllers(braking: str) -> list[tuple[str, Callable[[], Any]]]:
    """(name, factory) of the controllers of the suite leaderboard: each is told each episode's scenario
    (the operator and the MPC use it; the shipped PPO policies run as trained, on the nominal cycle)."""
    from agents.evaluate import default_policy_path, load_controller
    from mpc.controller.mpc import MPCConfig, MPCController

    out: list[tuple[str, Callable[[], Any]]] = [
        ("operator", lambda: load_controller("operator", braking)),
        ("mpc (min time)", lambda: MPCController(braking, config=MPCConfig(mode="time"))),
    ]
    if default_policy_path(braking).exists():
        out.append(("ppo (nominal-trained)", lambda: load_controller("ppo", braking)))
    return out


# the suite leaderboard's targets of the target-conditioned controllers (#14): label, ratio to the episode's T_min
TARGETS = (("fastest", 1.0), ("1.15 T_min", 1.15), ("1.5 T_min", 1.5))


def target_controllers(braking: str) -> list[tuple[str, Callable[[], Any]]]:
    """(name, factory) of the shipped target-conditioned controllers (the learned ones), run at each of
    :data:`TARGETS`: the target-conditioned PPO (per step, and one plan per cycle) and the behaviour-cloned MPC,
    where shipped."""
    from agents.evaluate import default_policy_path, load_controller

    out: list[tuple[str, Callable[[], Any]]] = []
    for name, spec, kind in (("ppo (target-conditioned)", "ppo", "ppo-target"), ("ppo (plan)", "plan", "plan"),
                             ("bc (imitation)", "bc", "bc")):
        if default_policy_path(braking, kind).exists():
            out.append((name, lambda spec=spec: load_controller(spec, braking, targeted=True)))
    return out


def collect_suite(suite: str = SUITE, sample: int | None = SUITE_SAMPLE, cache: str | None = None,
                  controllers: Callable[[str], list[tuple[str, Callable[[], Any]]]] = suite_controllers,
                  brakings: tuple[str, ...] = BRAKINGS,
                  at_targets: Callable[[str], list[tuple[str, Callable[[], Any]]]] | None = target_controllers,
                  targets: tuple[tuple[str, float], ...] = TARGETS, isolate: bool = False,
                  keep: Path | None = None) -> dict[str, Any]:
    """Every controller on ``sample`` scenarios of the suite per braking alternative (None: all of them),
    each episode scored against its own scenario's optimum: the suite leaderboard's rows and episodes.
    ``at_targets``' controllers run at each of ``targets`` (a row each, with its lateness). ``isolate``:
    each controller's run in a worker process of its own (:func:`evaluation`); ``keep``: as there."""
    from wl_env.suites import load_suite

    s = load_suite(suite)
    rows, episodes = [], []
    for b in brakings:
        scenarios = list(s.spread(b, sample))
        runs = [(controllers, name, None, None) for name, _ in controllers(b)]
        runs += [(at_targets, name, label, ratio) for name, _ in (at_targets(b) if at_targets else [])
                 for label, ratio in targets]
        for listing, name, label, ratio in runs:
            log.info(f"[{suite} suite, {b}] {name}{'' if label is None else ', target ' + label}: "
                     f"{len(scenarios)} scenarios")
            ev = evaluation(listing, b, name, isolate, keep=keep, scenarios=scenarios, cache=cache, name=name,
                            target_ratio=ratio)
            sm = ev["summary"]
            rows.append({"controller": name, "braking": b, "target": label, "scenarios": len(scenarios),
                         "success_rate": sm["success_rate"],
                         "time_gap_median": sm["time_gap_median"], "time_gap_p90": sm["time_gap_p90"],
                         "fuel_gap_median": sm["fuel_gap_median"], "fuel_gap_p90": sm["fuel_gap_p90"],
                         "lateness_median": sm["lateness_median"], "max_violation": sm["max_violation"]})
            episodes += [{"controller": name, "braking": b, "target": label, "scenario": e["scenario"],
                          "success": e["success"], "T": e["T"], "fuel_g": e["fuel_g"], "T_min": e["T_min"],
                          "fuel_opt_g": e["fuel_opt_g"], "time_gap": e["time_gap"], "fuel_gap": e["fuel_gap"],
                          "target_time": e["target_time"], "lateness": e["lateness"]} for e in ev["per_episode"]]
    n_list = len(s.of(brakings[0]))
    return {"suite": suite, "version": s.version, "sample": sample, "full": sample is None or sample >= n_list,
            "scenarios_per_braking": n_list, "rows": rows, "episodes": episodes}


def evaluation(listing: Callable[[str], list[tuple[str, Callable[[], Any]]]], braking: str, controller: str,
               isolate: bool = False, keep: Path | None = None, **kwargs: Any) -> dict[str, Any]:
    """:func:`_evaluation`, kept in the folder ``keep`` once done (atomically, with its arguments' key and a
    checksum) and read back from there instead of run again: a `wl run` killed after some controllers goes on
    from there when run again (it ran every controller again, up to 10 min). A kept file that is not exactly
    one of these is run again."""
    key = _evaluation_key(listing, braking, controller, kwargs) if keep is not None else None
    if key is not None:
        kept = _read_kept(keep / f"{key}.json", key)
        if kept is not None:
            log.info(f"[{braking}] {controller}: the evaluation of an interrupted run, kept in {keep}")
            return kept
    result = _evaluation(listing, braking, controller, isolate, **kwargs)
    if key is not None:
        from wl_env.atomic_io import write_json_atomic

        keep.mkdir(parents=True, exist_ok=True)
        write_json_atomic(keep / f"{key}.json", {"key": key, "checksum": _kept_checksum(result), "result": result})
    return result


def _plain(o: Any) -> Any:
    """JSON of an evaluation's arguments (its key) and result: scenarios, fronts and arrays as their values."""
    if hasattr(o, "to_dict"):
        return o.to_dict()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    if hasattr(o, "__dict__"):
        return vars(o)
    return str(o)


# What the controllers drive with and the scores are measured against, besides the code: the shipped policies, the
# suites and the shipped optima. A kept evaluation is keyed by their content too, not by the version alone (stop 64
# shipped a new TC policy and bumped the version only after the review: an interrupted run's rows of the old one
# would have been reused).
_ROOT = Path(__file__).resolve().parents[1]
SHIPPED_DATA = (_ROOT / "agents" / "policies", _ROOT / "wl_env" / "suites", _ROOT / "mpc" / "benchmark" / "references")


@functools.cache
def shipped_data_digest(folders: tuple[Path, ...]) -> str:
    """sha256 over the names and contents of the files in ``folders`` (sorted; read once per process)."""
    import hashlib

    h = hashlib.sha256()
    for folder in folders:
        for path in sorted(p for p in Path(folder).rglob("*") if p.is_file() and "__pycache__" not in p.parts):
            h.update(f"{path.relative_to(folder.parent)}\0".encode())
            h.update(hashlib.sha256(path.read_bytes()).digest())
    return h.hexdigest()


def _evaluation_key(listing: Any, braking: str, controller: str, kwargs: dict[str, Any]) -> str:
    import hashlib

    from wl_env import __version__

    what = {"version": __version__, "format": RESULTS_FORMAT, "listing": f"{listing.__module__}.{listing.__qualname__}",
            "shipped": shipped_data_digest(SHIPPED_DATA), "braking": braking, "controller": controller, "kwargs": kwargs}
    return hashlib.sha256(json.dumps(what, sort_keys=True, default=_plain).encode()).hexdigest()[:32]


def _kept_checksum(result: Any) -> str:
    import hashlib

    text = json.dumps(result, sort_keys=True, separators=(",", ":"), default=_plain)
    return "sha256:" + hashlib.sha256(text.encode()).hexdigest()


def _read_kept(path: Path, key: str) -> dict[str, Any] | None:
    """The result kept at ``path`` for ``key``, or None (none, or not exactly what was written: a warning)."""
    if not path.is_file():
        return None
    try:  # (a regular file, bounded as a results.json, which holds every evaluation: a huge one was read whole)
        data = json.loads(read_regular_file(path, MAX_RESULTS_BYTES, "a kept evaluation holds"))
        if (isinstance(data, dict) and data.get("key") == key and isinstance(data.get("result"), dict)
                and data.get("checksum") == _kept_checksum(data["result"])):
            return data["result"]
        problem = "its key or checksum does not match"
    except (OSError, ValueError, RecursionError) as exc:
        problem = " ".join(str(exc).split())[:200]
    log.warning(f"{path}: not a kept evaluation ({problem}); running it again")
    return None


def _evaluation(listing: Callable[[str], list[tuple[str, Callable[[], Any]]]], braking: str, controller: str,
                isolate: bool = False, **kwargs: Any) -> dict[str, Any]:
    """:func:`agents.evaluate.evaluate_controller` of the ``controller`` so named in ``listing(braking)``, with
    ``kwargs``; every solver it built is dropped after it (the next controller plans with other NLPs).

    ``isolate``: the episodes in a worker process of its own (:func:`mpc.workers.run_in_workers`: Ctrl-C
    and a failure come back here), then their scores here, so that one controller's solvers, another's
    torch and the optima solved for their scores never share a heap, and each one's memory goes back to
    the OS when it is done: the main job's peak is then the largest of them plus this process's, not
    their sum (measured in docs/benchmarks.md). ``listing`` must then be a module-level function (the
    worker imports it by name)."""
    if not isolate:
        return _evaluate(listing, braking, controller, kwargs)
    if "<" in getattr(listing, "__qualname__", "<"):  # a lambda or a nested function: not importable by name
        raise ValueError(f"isolate=True needs listing to be a module-level function (the worker imports it), got {listing!r}")
    from agents.evaluate import score_evaluation
    from mpc.controller.solver import release_solvers
    from mpc.workers import run_in_workers

    job = ("wl.report:_evaluate", (listing, braking, controller, {**kwargs, "deferred": True}))
    result = run_in_workers({controller: job}, log_level=log.getEffectiveLevel())[controller]  # (its progress, as here)
    try:
        return score_evaluation(result, **{k: kwargs[k] for k in ("front", "cache", "solve", "unknown") if k in kwargs})
    finally:
        release_solvers()


def _evaluate(listing: Callable[[str], list[tuple[str, Callable[[], Any]]]], braking: str, controller: str,
              kwargs: dict[str, Any]) -> dict[str, Any]:
    from agents.evaluate import evaluate_controller
    from mpc.controller.solver import release_solvers

    named = dict(listing(braking))
    if controller not in named:
        raise ValueError(f"controller must be one of {sorted(named)} ({braking} braking), got {controller!r}")
    try:
        return evaluate_controller(named[controller](), braking, **kwargs)
    finally:
        release_solvers()


# ---------------------------------------------------------------------------------------------- collect
def collect(out_dir: str | Path = "results", cache: str | None = None,
            controllers: Callable[[str], list[tuple[str, Callable[[], Any]]]] = controllers,
            brakings: tuple[str, ...] = BRAKINGS, suite_sample: int | None = SUITE_SAMPLE,
            suite_controllers: Callable[[str], list[tuple[str, Callable[[], Any]]]] | None = suite_controllers,
            isolate: bool = False) -> dict[str, Any]:
    """Load (shipped) or solve the nominal fronts, run each controller from the nominal start and on a
    sample of the ``test`` suite (``suite_sample`` per braking alternative, None: all; ``suite_controllers``
    None: no suite), save ``results.json``.

    Every controller runs through :func:`agents.evaluate.evaluate_controller`, the same evaluation as
    ``wl evaluate``; with ``isolate``, each in a worker process of its own (:func:`evaluation`). Returns
    what was saved.
    """
    from mpc.benchmark.pareto import min_time_result, pareto_fronts
    from mpc.benchmark.reference import known_front
    from mpc.controller.solver import release_solvers
    from wl_env.atomic_io import write_json_atomic
    from wl_env.params import DEFAULT_PARAMS

    t_start = time.perf_counter()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    fronts, optima, rows, trajectories = {}, {}, [], []
    keep = out / KEEP_DIR  # (each controller's finished evaluation: a killed run goes on from there)
    known = {b: known_front(b, DEFAULT_PARAMS, cache) for b in brakings}
    missing = tuple(b for b in brakings if known[b] is None)
    solved = {b: known[b][0] for b in brakings if known[b] is not None}
    if missing:
        log.info(f"[benchmark] Pareto fronts, {' and '.join(missing)} braking (solved in parallel; cached after the first run)")
        solved.update(pareto_fronts(missing, cache=cache, progress=True))
    for b in brakings:
        front = solved[b]
        fronts[b] = dict(front.__dict__)
        opt = min_time_result(b, cache=cache)  # the time-optimal cycle's trajectory (cached)
        optima[b] = {"T": opt.T, "fuel_g": opt.fuel_g, "t": opt.t, "states": opt.states}
        # The minimum-time optimum leaves the fuel free where it costs no time; the reference a controller
        # is scored against is the front: minimum time, and the minimum fuel at each cycle time.
        rows.append({"controller": "optimum (min time)", "braking": b, "T": opt.T, "fuel_g": opt.fuel_g,
                     "time_gap": 0.0, "fuel_gap": opt.fuel_g / front.fuel_at(opt.T) - 1.0, "max_violation": 0.0,
                     "success": True})
        rows.append({"controller": "optimum (min fuel at 1.001 T_min)", "braking": b, "T": front.T[0],
                     "fuel_g": front.fuel_g[0], "time_gap": front.T[0] / front.T_min - 1.0, "fuel_gap": 0.0,
                     "max_violation": 0.0, "success": True})
        release_solvers()  # (the optima's OCPs, if solved here)
        for name, _ in controllers(b):
            log.info(f"[{b}] {name}")
            ev = evaluation(controllers, b, name, isolate, keep=keep, episodes=1, seed=0, front=front, cache=cache,
                            trajectories=True)
            ep = ev["per_episode"][0]
            rows.append({"controller": name, "braking": b, "T": ep["T"], "fuel_g": ep["fuel_g"],
                         "time_gap": ep["time_gap"], "fuel_gap": ep["fuel_gap"], "max_violation": ep["max_violation"],
                         "success": ep["success"], "completed": ep["completed"]})
            traj = ep["trajectory"]
            trajectories.append({"controller": name, "braking": b, "t": traj["t"], "states": traj["states"]})
    suite = (collect_suite(sample=suite_sample, cache=cache, controllers=suite_controllers, brakings=brakings,
                           isolate=isolate, keep=keep)
             if suite_controllers is not None else None)
    results = {"format": RESULTS_FORMAT, "brakings": list(brakings), "rows": rows, "fronts": fronts,
               "optima": optima, "trajectories": trajectories, "suite": suite,
               "wall_time_s": time.perf_counter() - t_start}
    write_json_atomic(out / RESULTS_FILE, results)
    shutil.rmtree(keep, ignore_errors=True)  # (done: a later run evaluates afresh)
    return results


MAX_RESULTS_BYTES = 64 * 2**20  # (a full-suite results.json is a few MB; a 2 GB file was read whole: 4 GB, 10 s)
# curves a figure draws, at most: a trajectory each, a suite label (controller and target) each; `wl run` writes 8 and
# ~20 (a 0.6 MB file of 5000 trajectories took 44 s to draw, 64 MB's would take hours)
MAX_CURVES = 200


def load_results(folder: str | Path) -> dict[str, Any]:
    """``results.json`` of a ``wl run`` folder, checked to hold everything :func:`render` draws."""
    path = Path(folder) / RESULTS_FILE
    try:
        raw = read_regular_file(path, MAX_RESULTS_BYTES, "a results.json of `wl run` holds")
    except FileNotFoundError:
        if os.path.lexists(path):  # (a dangling link was "no results.json")
            raise ValueError(f"{path} is not a regular file (`wl run --out {folder}` writes one)") from None
        raise FileNotFoundError(f"no {RESULTS_FILE} in {folder} (write one with `wl run --out {folder}`)") from None
    except ValueError as exc:  # (a pipe, a device or a folder was "no results.json"; a 2 GB file was read whole)
        raise ValueError(f"{path} is {exc} (`wl run --out {folder}` writes one)") from None
    try:
        results = json.loads(raw.decode("utf-8"))
    except (ValueError, OSError) as exc:  # (JSONDecodeError, UnicodeDecodeError, an int of too many digits)
        raise ValueError(f"{path} is not valid JSON: {' '.join(str(exc).split())[:200]}") from None
    except RecursionError:  # (a RuntimeError)
        raise ValueError(f"{path} is not valid JSON: nested too deeply") from None

    problem = _problem(results)
    if problem:
        raise ValueError(f"{path} cannot be rendered: {problem} (`wl run` writes a complete one)")
    return results


def _plain_text(text: str) -> str:
    """``text`` as matplotlib draws it literally: a ``$`` in a controller's or a suite's name started mathtext (a
    parse error naming neither the file nor the field)."""
    return text.replace("$", r"\$")


def _printable(text: Any) -> str:
    """``text`` with each control character (a newline ended a table row or a title) as a space."""
    return "".join(c if c.isprintable() else " " for c in str(text))


def _cell(text: Any) -> str:
    """``text`` as one markdown table cell shows it literally: a newline (or another control character) in a
    controller's name ended the row, and a ``|`` split the cell, shifting every column after it (each kept in
    results.json as given, as ``$`` is for the figures, :func:`_plain_text`). Valid names are unchanged."""
    text = _printable(text)
    # a | escaped, and the backslashes just before it doubled (they would escape the escape); other backslashes stay
    # as they are (a name like $\frac{$ is drawn as it is)
    return re.sub(r"(\\*)\|", lambda m: 2 * m.group(1) + "\\|", text)


def _problem(results: Any) -> str | None:
    """What keeps :func:`render` from drawing ``results``, or None."""
    from mpc.benchmark.pareto import check_front

    if not isinstance(results, dict):
        return "not a JSON object"
    if results.get("format") != RESULTS_FORMAT:
        return f"format {results.get('format')!r}, this version renders format {RESULTS_FORMAT}"
    try:
        if (not results["brakings"] or not set(results["brakings"]) <= set(BRAKINGS)
                or len(set(results["brakings"])) != len(results["brakings"])):  # (twice: a staging file missing)
            return f"brakings {results['brakings']!r}, expected some of {list(BRAKINGS)}"
        for b in results["brakings"]:
            front = results["fronts"][b]
            if len(front["T"]) != len(front["fuel_g"]) or len(front["T"]) < 2:
                return f"the {b} front needs as many fuels as cycle times, at least 2"
            if not all(map(is_real_number, [front["T_min"], front["T_fuel_opt"], *front["T"], *front["fuel_g"]])):
                return f"the {b} front holds a value that is not a finite number"
            problem = check_front(front)  # what a cached front must be: times rising from T_min, fuel falling
            if problem:
                return f"the {b} front: {problem}"
            if front["braking"] != b:  # (the other braking's front was drawn as this one's)
                return f"the {b} front is the {front['braking']!r} braking's"
            _check_trajectory(results["optima"][b])
        for r in results["rows"]:
            missing = [k for k in ROW_KEYS if k not in r]
            if missing:
                return f"a row lacks {missing}"
            if not (isinstance(r["controller"], str) and r["braking"] in BRAKINGS and isinstance(r["success"], bool)):
                return "a row's controller is not a name, its braking not one of the brakings or its success not a bool"
            if not (all(map(is_real_number, (r["T"], r["fuel_g"], r["max_violation"])))
                    and all(v is None or is_real_number(v) for v in (r["time_gap"], r["fuel_gap"]))):
                return f"a row of {r['controller']!r} holds a value that is not a finite number"
        if len(results["trajectories"]) > MAX_CURVES:
            return (f"{len(results['trajectories'])} trajectories, more than the {MAX_CURVES} its figures draw "
                    "(one per controller and braking)")
        for tr in results["trajectories"]:
            if not (isinstance(tr["controller"], str) and tr["braking"] in BRAKINGS):
                return "a trajectory's controller is not a name or its braking not one of the brakings"
            _check_trajectory(tr)
        if not is_real_number(results["wall_time_s"]):
            return "wall_time_s is not a number"
        suite = results.get("suite")
        if suite is not None:
            if not (isinstance(suite["suite"], str) and isinstance(suite["full"], bool)
                    and all(is_real_number(suite[k]) for k in ("version", "scenarios_per_braking"))
                    and (suite["sample"] is None or is_real_number(suite["sample"]))):
                return "the suite's name, version, sample, full or scenarios_per_braking is malformed"
            for r in suite["rows"]:
                if not (isinstance(r["controller"], str) and r["braking"] in BRAKINGS
                        and all(map(is_real_number, (r["scenarios"], r["success_rate"], r["max_violation"])))
                        and all(r.get(k) is None or is_real_number(r[k]) for k in (
                            "time_gap_median", "time_gap_p90", "fuel_gap_median", "fuel_gap_p90", "lateness_median"))):
                    return f"a suite row of {r['controller']!r} holds a value that is not a finite number"
            for e in suite["episodes"]:
                if not (isinstance(e["controller"], str) and e["braking"] in BRAKINGS and isinstance(e["success"], bool)
                        and (e["fuel_gap"] is None or is_real_number(e["fuel_gap"]))
                        and (e["scenario"] is None or (isinstance(e["scenario"], dict) and all(
                            is_real_number(e["scenario"][k]) for k in ("payload", "reverse_distance", "forward_distance"))))):
                    return "a suite episode's controller, braking, success, fuel_gap or scenario is malformed"
            labels = {(e["controller"], str(e.get("target"))) for e in suite["episodes"]}
            if len(labels) > MAX_CURVES:
                return (f"the suite's episodes name {len(labels)} controllers and targets, more than the {MAX_CURVES} "
                        "its figure draws")
    except (KeyError, TypeError, IndexError, OverflowError) as exc:
        return f"missing or malformed entry {exc}"
    except ValueError as exc:
        return str(exc)
    return None


def _check_trajectory(d: dict[str, Any]) -> None:
    if not (isinstance(d["t"], list) and len(d["t"]) >= 2 and all(map(is_real_number, d["t"]))):  # (an empty one
        raise ValueError("a trajectory's times t are not a list of at least 2 finite numbers")    # failed in the figure)
    states = d["states"]  # (numbers, not numbers in strings: np.asarray(dtype=float) took "81.6", and the figure failed)
    if not (isinstance(states, list) and len(states) == len(d["t"])
            and all(isinstance(row, list) and len(row) == 4 and all(map(is_real_number, row)) for row in states)):
        raise ValueError(f"its states are not {len(d['t'])} rows of 4 finite numbers, one per time")


# ---------------------------------------------------------------------------------------------- render
def _gap(v: float | None) -> str:
    return "n/a" if v is None or v != v else f"{100 * v:+.1f} %"


def render(results: dict[str, Any], out_dir: str | Path = "results",
           inputs: tuple[str | Path, ...] = ()) -> list[Path]:
    """Leaderboard, Pareto figure and trajectory figures from :func:`collect`'s results; returns the files.
    They are drawn in a staging folder inside ``out_dir`` and moved into it together at the end: an interrupt or
    a failure part-way leaves the report there as it was (it left 4 of 5 new files beside the old fifth). No file
    of the report may be ``out_dir``'s results.json or one of ``inputs`` (by any path, links too)."""
    from mpc import interrupt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=".report-", dir=out))
    try:
        drawn = _draw(results, out, staging, (out / RESULTS_FILE, *map(Path, inputs)))
        # (a symbolic link in the folder is written through, as --out's are, each file atomically: a copy across file
        # systems was written in place. An interrupt between two files left a report of old and new ones: it is
        # taken once they are all in place)
        with interrupt.deferred():
            return [_place(f, out / f.name) for f in drawn]
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def _place(drawn: Path, path: Path) -> Path:
    """The staged file ``drawn`` as ``path``, atomically (a symbolic link written through)."""
    from wl_env.atomic_io import atomic_path

    with atomic_path(path) as tmp:  # (beside the target: a link's may lie on another file system)
        shutil.copyfile(drawn, tmp)
    return Path(os.path.realpath(path))


def report_files(brakings: Any, suite: bool) -> list[str]:
    """The names of the files :func:`render` writes for these braking alternatives (and the suite's figure)."""
    return ["leaderboard.md", "pareto.png", *(f"trajectories_{b}.png" for b in brakings)] + (
        ["suite_gaps.png"] if suite else [])


def check_report_files(out: Path, names: list[str], inputs: tuple[Path, ...] = ()) -> None:
    """ValueError naming the file if one of the report's files ``names`` in ``out`` cannot be written (a folder, a
    pipe, ...) or is one of ``inputs`` by any path, links too, also a link to an input not written yet (`wl report`
    wrote its leaderboard over results.json through a link named leaderboard.md)."""
    from wl_env.atomic_io import check_not_an_input

    protected = {os.path.realpath(p) for p in inputs}
    for name in names:
        check_output_file(out / name, "the report's file")
        if os.path.realpath(out / name) in protected:
            raise ValueError(f"the report's file {out / name} is the input file {os.path.realpath(out / name)}: the "
                             "report would replace it; give another path")
        check_not_an_input(out / name, list(inputs), "the report's file")


def _draw(results: dict[str, Any], out: Path, staging: Path, inputs: tuple[Path, ...] = ()) -> list[Path]:
    """:func:`render`'s files, written in ``staging`` (the names checked against ``out``, and to be none of
    ``inputs``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mpc.benchmark.pareto import ParetoFront

    brakings, rows, fronts = results["brakings"], results["rows"], results["fronts"]
    # (each checked before any is written: a folder at pareto.png left half a report)
    check_report_files(out, report_files(brakings, bool(results.get("suite"))), inputs)
    written = []
    # ---- leaderboard
    lines = ["# Leaderboard", "", "Cycle time and fuel of each controller in `WheelLoader-v1`, scored against the "
             "optimal control benchmark: time gap to the minimum cycle time, fuel gap to the minimum fuel at the "
             "same cycle time (the Pareto front). Violation: largest relative excess over the deceleration and "
             "speed limits. Success: cycle completed with the reversing point and the end within 5 cm and the "
             "bucket within 2 cm of 5 m.", "",
             "| controller | braking | cycle time (s) | fuel (g) | time gap | fuel gap | violation | success |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {_cell(r['controller'])} | {r['braking']} | {r['T']:.2f} | {r['fuel_g']:.1f} | {_gap(r['time_gap'])} | "
                     f"{_gap(r['fuel_gap'])} | {100 * r['max_violation']:.1f} % | {'yes' if r['success'] else 'no'} |")
    front_text = ", ".join(f"{b}: {len(fronts[b]['T'])} points, T {fronts[b]['T_min']:.2f}-{fronts[b]['T_fuel_opt']:.2f} s"
                           for b in brakings)
    lines += ["", f"Pareto fronts: {front_text}."]
    suite = results.get("suite")
    if suite:
        lines += suite_table(suite)
        written.append(suite_figure(suite, staging / "suite_gaps.png"))
    lines += ["", f"Generated by `wl run` in {results['wall_time_s']:.0f} s."]
    written.append(write_atomic(staging / "leaderboard.md", "\n".join(lines) + "\n"))
    # ---- Pareto figure with the controllers' points
    fig, ax = plt.subplots(figsize=(7, 4.5))
    colors = {"service": "tab:blue", "tc": "tab:red"}
    markers = {"operator": "s", "mpc (min time)": "^", "mpc (T = 11 s)": "v", "ppo": "o"}
    for b in brakings:
        front = ParetoFront(**{k: v for k, v in fronts[b].items() if k in ParetoFront.__dataclass_fields__})
        T_grid = np.linspace(front.T[0], front.T[-1], 200)[:-1]  # interpolated as the scores are (fuel_at)
        ax.plot(T_grid, [front.fuel_at(T) for T in T_grid], "-", color=colors[b], label=f"Pareto front, {b}")
        ax.plot(front.T, front.fuel_g, ".", color=colors[b], ms=5)
        for r in rows:
            if r["braking"] == b and r["controller"] in markers and r.get("completed"):
                ax.plot(r["T"], r["fuel_g"], markers[r["controller"]], color=colors[b], mfc="none", ms=8,
                        label=_plain_text(f"{r['controller']}, {b}"))
    ax.set_xlabel("cycle time (s)")
    ax.set_ylabel("fuel (g)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    written.append(save_figure(fig, staging / "pareto.png", dpi=130))
    plt.close(fig)
    # ---- trajectories beside the time-optimal ones
    labels = ["engine speed (rpm)", "vehicle speed (m/s)", "bucket height (m)", "bucket speed (m/s)"]
    scale = [30 / np.pi, 1, 1, 1]
    for b in brakings:
        fig, axes = plt.subplots(2, 2, figsize=(10, 6), sharex=True)
        opt = np.asarray(results["optima"][b]["states"])
        for i, ax in enumerate(axes.ravel()):
            ax.plot(results["optima"][b]["t"], opt[:, i] * scale[i], "k-", lw=2, label="optimum (min time)")
            for tr in results["trajectories"]:
                if tr["braking"] == b:
                    ax.plot(tr["t"], np.asarray(tr["states"])[:, i] * scale[i], lw=1, label=_plain_text(tr["controller"]))
            ax.set_ylabel(labels[i])
            ax.grid(alpha=0.3)
        for ax in axes[1]:
            ax.set_xlabel("time (s)")
        axes[0, 0].legend(fontsize=7)
        fig.suptitle(f"{b} braking: controllers against the time-optimal cycle")
        fig.tight_layout()
        written.append(save_figure(fig, staging / f"trajectories_{b}.png", dpi=120))
        plt.close(fig)
    return written


def _share(v: float | None) -> str:
    return "-" if v is None else f"{100 * v:.1f} %"


def suite_table(suite: dict[str, Any]) -> list[str]:
    """The suite leaderboard's lines (markdown)."""
    which = (f"all {suite['scenarios_per_braking']} scenarios" if suite["full"] else
             f"a fixed sample of {suite['sample']} of its {suite['scenarios_per_braking']} scenarios (`wl run "
             f"--full-suite` runs all)")
    lines = ["", f"## The `{_printable(suite['suite'])}` suite (v{suite['version']}): {which} per braking alternative", "",
             "Each episode from its scenario's own start, scored against that scenario's own optimum (shipped with "
             "the package). Gaps over the successful episodes (median, p90); the success rate beside them.", "",
             "The target-conditioned controllers run at three targets per scenario (fastest: T_min itself; 1.15 "
             "and 1.5 times the scenario's T_min); lateness: by how much the cycle ran past its target, as a "
             "share of it (median over the completed cycles).", "",
             "| controller | braking | target | scenarios | success | time gap median | time gap p90 | "
             "fuel gap median | fuel gap p90 | lateness median | max violation |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in suite["rows"]:
        lines.append(f"| {_cell(r['controller'])} | {r['braking']} | {_cell(r.get('target') or '-')} | {r['scenarios']} | "
                     f"{100 * r['success_rate']:.0f} % | {_gap(r['time_gap_median'])} | {_gap(r['time_gap_p90'])} | "
                     f"{_gap(r['fuel_gap_median'])} | {_gap(r['fuel_gap_p90'])} | "
                     f"{_share(r.get('lateness_median'))} | "
                     f"{100 * r['max_violation']:.1f} % |")
    return lines


def suite_figure(suite: dict[str, Any], path: Path) -> Path:
    """Fuel gap against the scenario's payload and its total distance, per controller and braking."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    def label(e: dict[str, Any]) -> str:
        return e["controller"] if not e.get("target") else f"{e['controller']} at {e['target']}"

    names = sorted({label(e) for e in suite["episodes"]})
    for k, name in enumerate(names):
        for b, marker in (("service", "o"), ("tc", "^")):
            eps = [e for e in suite["episodes"] if label(e) == name and e["braking"] == b
                   and e["success"] and e["fuel_gap"] is not None and e["scenario"]]
            if not eps:
                continue
            gap = [100 * e["fuel_gap"] for e in eps]
            axes[0].plot([e["scenario"]["payload"] / 1000 for e in eps], gap, marker, color=f"C{k}", mfc="none",
                         label=_plain_text(f"{name}, {b}"))
            axes[1].plot([e["scenario"]["reverse_distance"] + e["scenario"]["forward_distance"] for e in eps], gap,
                         marker, color=f"C{k}", mfc="none")
    axes[0].set_xlabel("payload (t)")
    axes[1].set_xlabel("reverse + forward distance (m)")
    axes[0].set_ylabel("fuel gap to the scenario's optimum (%)")
    for ax in axes:
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle(_plain_text(f"`{suite['suite']}` suite: fuel gap per scenario (successful episodes)"))
    fig.tight_layout()
    out = save_figure(fig, path, dpi=120)
    plt.close(fig)
    return out


def run_all(out_dir: str | Path = "results", cache: str | None = None, full_suite: bool = False) -> dict[str, Any]:
    """``wl run``: :func:`collect` (each controller in a worker process of its own) then :func:`render` into
    ``out_dir``; returns the results."""
    t_start = time.perf_counter()
    results = collect(out_dir, cache=cache, suite_sample=None if full_suite else SUITE_SAMPLE, isolate=True)
    render(results, out_dir)
    log.info(f"report written to {out_dir}/ in {time.perf_counter() - t_start:.0f} s")
    return results
