"""``wl``: the command line of wheel-loader-gym (the top floor: it imports every package, none imports it).

Each subcommand is a small function over the packages; errors a user can fix come out as one line
``wl: error: ...`` with exit code 2, never as a traceback. Every option is checked before any work
(numbers for type, finiteness and range, output paths for being writable); Ctrl-C stops the work within
about a second with exit code 130 (SIGTERM: 143) and writes no result (:mod:`mpc.interrupt`). Progress goes through
:mod:`logging` to stderr.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import math
import os
import shlex
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)


class UsageError(Exception):
    """A command line argparse rejects, reported like every other user error (one line, exit code 2)."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # type: ignore[override]
        raise UsageError(f"{message} (see `{self.prog} --help`)")

    def parse_known_args(self, args: Any = None, namespace: Any = None) -> Any:
        ns, extras = super().parse_known_args(args, namespace)
        # argparse (< 3.12) drops a value of "--" (``--time=--``) and stores [] without calling the type
        for action in self._actions:
            if action.nargs is None and action.option_strings and isinstance(getattr(ns, action.dest, None), list):
                self.error(f"argument {'/'.join(action.option_strings)}: expected one value")
        return ns, extras


def _params_cmd(args: argparse.Namespace) -> int:
    from wl_env.params import PROVENANCE, LoaderParams

    if args.set is not None and not args.set.strip():  # (not `if args.set`: an empty --set printed the defaults)
        raise ValueError("--set is empty: give a JSON object of LoaderParams fields")
    overrides = _json_option(args.set, "--set") if args.set is not None else {}
    if not isinstance(overrides, dict):
        raise ValueError(f"--set must be a JSON object of LoaderParams fields, got {type(overrides).__name__}")
    p = LoaderParams.from_dict(overrides)
    if args.json:
        print(json.dumps(p.to_dict(), indent=1))
        return 0
    for name, value in p.to_dict().items():
        unit, source = PROVENANCE.get(name, ("", ""))
        print(f"{name:15s} {str(value):45s} {unit:30s} {source}")
    return 0


# Output folders a command created for its outputs; removed again where it stops (interrupted, or an error) and left
# them empty (an interrupted `wl pareto` left an empty --out folder).
_CREATED: list[Path] = []


def _created_by(make: Callable[[], Path], folder: Path) -> Path:
    from wl_env.atomic_io import missing_folders

    missing = missing_folders(folder)
    out = make()
    _CREATED.extend(reversed(missing))
    return out


def _out_file(path: str, option: str = "--out") -> Path:
    """An output file's path, checked before the work: not a folder, its folder creatable and writable."""
    from wl_env.atomic_io import check_output_file

    return _created_by(lambda: check_output_file(path, option), Path(path).parent)


def _result_file(args: argparse.Namespace) -> Path | None:
    """``--out``'s file, checked before the work, or None: no ``--out`` (or ``-``) writes the JSON to stdout."""
    if args.out is None or args.out == "-":
        return None
    out = _out_file(args.out)
    check_not_an_input(out, _scenario_file(args), "--out")
    return out


@contextlib.contextmanager
def _stdout_for_the_result(out: Path | None) -> Iterator[None]:
    """Without ``--out``, file descriptor 1 goes to stderr while the work runs, so that the JSON is all stdout
    holds (IPOPT's banner and other C code write to fd 1 directly)."""
    if out is not None:
        yield
        return
    sys.stdout.flush()
    saved = os.dup(1)
    os.dup2(2, 1)
    try:
        yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)


def _put_result(result: dict[str, Any], out: Path | None, line: str) -> None:
    """The result to ``out`` (atomically) with its summary line on stdout, or, without ``--out``, the JSON to
    stdout and the line to stderr."""
    from wl_env.atomic_io import json_text, write_atomic

    try:  # (a value JSON cannot hold was json's TypeError, a traceback; nothing is written then)
        text = json_text(result)
    except (TypeError, ValueError) as exc:
        raise RuntimeError(f"the result cannot be written as JSON ({_one_line(exc)}); nothing was written") from exc
    if out is None:
        print(line, file=sys.stderr)
        sys.stdout.write(text)
        sys.stdout.flush()
    else:
        write_atomic(out, text)
        print(f"{line} -> {out}")


def _out_dir(path: str, option: str = "--out") -> Path:
    """An output folder, created and probed for writing before the work."""
    from wl_env.atomic_io import check_output_folder

    return _created_by(lambda: check_output_folder(path, f"{option} {path}"), Path(path))


def check_not_an_input(out: Path, inputs: list[Path], option: str) -> None:
    from wl_env.atomic_io import check_not_an_input as check  # (imported late, as the CLI's other modules)

    check(out, inputs, option)


def _scenario_file(args: argparse.Namespace) -> list[Path]:
    """The --scenario's file, if it names one (not JSON text)."""
    text = (getattr(args, "scenario", None) or "").strip()
    return [Path(text)] if text and not text.startswith(("{", "[")) else []


def _remove_empty_created() -> None:
    """The folders this command created and left empty, removed (the deepest first)."""
    from wl_env.atomic_io import remove_empty_folders

    remove_empty_folders(_CREATED[::-1])
    _CREATED.clear()


def _ocp_cmd(args: argparse.Namespace) -> int:
    from mpc.benchmark.ocp import OCPSettings, check_cycle_time, solve_ocp
    from mpc.benchmark.pareto import save_result

    objective = {"time": "time", "fuel": "fuel", "weighted": "weighted"}[args.objective]
    if args.time is not None:
        if args.objective != "fuel":
            raise ValueError("--time fixes the cycle time of the minimum-fuel problem: use it with --objective fuel")
        check_cycle_time(args.time, "--time")  # before the work: a finite time the OCP can hold
        objective = "fuel_at_time"
    if args.w_fuel is not None and args.objective != "weighted":
        raise ValueError(f"--w-fuel is the fuel weight of --objective weighted; with --objective {args.objective} "
                         "it would be ignored")
    if args.objective == "weighted" and args.w_fuel is None:
        raise ValueError("--objective weighted needs --w-fuel W (0..1, the fuel weight W1; W2 = 1 - W1)")
    params = _params_from(args)
    scenario = _scenario_from(args)
    out = _out_file(args.out)
    check_not_an_input(out, _scenario_file(args), "--out")
    settings = OCPSettings(hessian=args.hessian) if args.hessian else None
    braking = scenario.braking if scenario is not None else args.braking or "service"
    log.info(f"solving the {braking} {objective} OCP ...")
    r = solve_ocp(braking, objective, T=args.time, w_fuel=args.w_fuel, params=params, settings=settings,
                  scenario=scenario)
    save_result(r, out)
    v = r.verification
    print(f"{braking} {objective}: T = {r.T:.3f} s, fuel = {r.fuel_g:.2f} g, phases "
          f"{', '.join(f'{d:.2f}' for d in r.phase_durations)} s, {r.iterations} iterations, {r.wall_time:.2f} s; "
          f"re-simulated: end position {100 * v['final_position_error_m']:+.1f} cm, height "
          f"{100 * v['final_height_error_m']:+.1f} cm, max violation {100 * v['max_violation']:.2f} % -> {args.out}")
    return 0


def _pareto_cmd(args: argparse.Namespace) -> int:
    from mpc.benchmark.pareto import pareto_fronts

    params = _params_from(args)
    scenario = _scenario_from(args, braking_given=args.braking not in (None, "both"))
    named = None if scenario is None else _scenario_braking(args)
    if named is not None and args.braking == "both":  # (both were solved: the scenario's braking dropped unsaid)
        raise ValueError(f"--braking both contradicts the --scenario's braking {named!r}")
    if scenario is not None:  # the scenario's cycle on the machine: both alternatives unless it or --braking says one
        from wl_env.params import resolve

        params = scenario.params(resolve(params))
    if args.cache is not None:  # (before --out: a bad --cache left a new, empty --out folder behind)
        _out_dir(args.cache, "--cache")
    out = _out_dir(args.out)
    brakings = (named,) if named is not None and args.braking is None else (
        ("service", "tc") if args.braking in (None, "both") else (args.braking,))
    for b in brakings:  # (each front's file before any solve: a folder in the way failed after both, one written)
        check_not_an_input(_out_file(str(out / f"pareto_{b}.json")), _scenario_file(args), "--out")
    fronts = pareto_fronts(brakings, n_points=args.points, params=params, cache=args.cache,
                           use_cache=not args.no_cache, progress=True)  # in parallel processes
    for b, front in fronts.items():
        path = front.save(out / f"pareto_{b}.json")
        print(f"{b}: {len(front.T)} points, T {front.T_min:.3f}..{front.T_fuel_opt:.3f} s, fuel "
              f"{front.fuel_g[0]:.2f}..{front.fuel_min_g:.2f} g -> {path}")
    return 0


def _check_target_reachable(target_time: float | None, scenarios: list[Any]) -> None:
    """A --target-time under a cycle's minimum time, refused now by name (the MPC found it out after seconds of
    planning, naming MPCConfig.target_time; `wl evaluate` blamed the controller): against the T_min estimate of
    each scenario (wl_env.suites.min_time, within 0.8 % on the `test` optima; 2 % allowed)."""
    from wl_env.suites.min_time import estimate_min_time

    for sc in [] if target_time is None else scenarios:
        t_min = estimate_min_time(sc)
        if target_time < 0.98 * t_min:
            raise ValueError(f"--target-time {target_time:g} s lies below the minimum cycle time of the {sc.label()} "
                             f"cycle (about {t_min:.2f} s with {sc.braking} braking)")


def _mpc_cmd(args: argparse.Namespace) -> int:
    from mpc.controller.mpc import AUTO, MPCConfig, run_closed_loop
    from wl_env.scenario import Scenario

    if args.cache is not None:  # (before --out, whose folder its check may create)
        _out_dir(args.cache, "--cache")
    params = _params_from(args)  # (checked now: a bad one failed after --out's folder and the log line)
    if args.realtime and args.deadline_ms is not None:
        raise ValueError("--realtime and --deadline-ms exclude each other: a real-time step's deadline is its interval")
    if args.horizon_steps is not None and (args.realtime or args.deadline_ms is not None):
        raise ValueError("--horizon-steps runs the synchronous controller: not with --realtime or --deadline-ms")
    full = args.full_horizon or args.realtime or args.deadline_ms is not None  # (the default horizon is short otherwise)
    short_only = (("--horizon-solver", args.horizon_solver not in (None, "ipopt")),
                  ("--replan-lag-steps", args.replan_lag_steps), ("--replan-in-step", args.replan_in_step))
    for flag, value in short_only:
        if value and full:
            raise ValueError(f"{flag} acts on the short horizons: not with --full-horizon, --realtime or --deadline-ms")
    horizon = None if args.full_horizon else AUTO if args.horizon_steps is None else args.horizon_steps
    lag = None if args.replan_in_step else args.replan_lag_steps or AUTO
    rt = {"deadline_ms": args.deadline_ms, "realtime": args.realtime, "replan_lag_steps": lag, "horizon_steps": horizon,
          "horizon_solver": args.horizon_solver or AUTO, "safety_filter": not args.no_safety_filter,
          **({"rate_weight": tuple(args.rate_weight)} if args.rate_weight else {})}
    if args.target_time is not None:
        config = MPCConfig(mode="target_time", target_time=args.target_time, **rt)
    elif args.w_fuel is not None:
        config = MPCConfig(mode="weighted", w_fuel=args.w_fuel, **rt)
    else:
        config = MPCConfig(mode="time", **rt)
    plant = None
    if (args.payload_scale != 1.0 or args.rolling_scale != 1.0) and args.scenario is not None:
        raise ValueError("--payload-scale and --rolling-scale scale the nominal plant; a --scenario sets the plant's "
                         "payload and rolling_resistance itself (with --mismatch the model keeps the nominal ones)")
    if args.payload_scale != 1.0 or args.rolling_scale != 1.0:
        from wl_env.params import resolve

        machine = resolve(params)
        try:
            plant = machine.variant(payload_scale=args.payload_scale, rolling_scale=args.rolling_scale)
        except ValueError as exc:  # (the machine's field alone would not say which option scaled it)
            raise ValueError(f"--payload-scale {args.payload_scale:g} / --rolling-scale {args.rolling_scale:g} give a "
                             f"plant out of range: {exc}") from None
    scenario = _scenario_from(args)
    braking = scenario.braking if scenario is not None else args.braking or "service"
    if args.mismatch and scenario is None:
        raise ValueError("--mismatch plans a --scenario's cycle with the nominal payload and rolling resistance: "
                         "give --scenario")
    if args.params is None:  # (the estimate knows the specification's machine)
        _check_target_reachable(args.target_time, [scenario or Scenario.nominal(braking)])
    out = _result_file(args)  # (after the other options: its check may create its folder)
    log.info(f"MPC ({config.mode}) driving the {braking} cycle ...")
    with _stdout_for_the_result(out):
        result = run_closed_loop(braking, config, params=params, plant_params=plant,
                                 score=not args.no_score, cache=args.cache, scenario=scenario, mismatch=args.mismatch)
    r = result.to_dict()
    st = r["solve_time"]
    line = (f"{braking} MPC ({config.mode}): T = {r['T']:.2f} s, fuel = {r['fuel_g']:.2f} g, success = {r['success']}, "
            f"solve time median {1e3 * st['median_s']:.1f} ms, p99 {1e3 * st['p99_s']:.1f} ms, max {1e3 * st['max_s']:.1f} ms, "
            + (f"{st['fallbacks']} steps on an overdue plan (the worker's solves: median "
               f"{1e3 * st['background_median_s']:.1f} ms, max {1e3 * st['background_max_s']:.0f} ms)" if config.realtime
               else f"{st['fallbacks']} fallbacks ({st['deadline_misses']} past the deadline)")
            + (f", {st['replans']} steps planned the whole cycle again" if config.horizon else "")
            + (f", {st['safety_eased']} controls eased by the safety filter" if config.safety_filter else ""))
    if r["score"] is not None:
        line += f"; time gap {100 * r['score']['time_gap']:+.2f} %, fuel gap {100 * r['score']['fuel_gap']:+.2f} %"
    _put_result(r, out, line)
    return 0 if r["completed"] else 1


def _evaluate_cmd(args: argparse.Namespace) -> int:
    from agents.evaluate import aggregate, controller_files, evaluate_controller, load_controller, summary_line
    from wl_env.scenario import Scenario
    from wl_env.suites import MAX_SAMPLE, load_suite

    if args.cache is not None:
        _out_dir(args.cache, "--cache")
    scenario = _scenario_from(args)
    if scenario is not None and args.suite:
        raise ValueError("give --scenario or --suite, not both")
    braking = scenario.braking if scenario is not None else args.braking or "service"
    if args.sample and not args.suite:
        raise ValueError("--sample N takes N scenarios of a --suite: give --suite")
    if args.suite and (args.episodes is not None or args.init_noise is not None):  # (they were ignored without a word)
        raise ValueError("--episodes and --init-noise set the episodes of one scenario; with --suite each scenario "
                         "runs once from its own start: leave them out (--sample N takes N scenarios)")
    episodes = 10 if args.episodes is None else args.episodes
    init_noise = 1.0 if args.init_noise is None else args.init_noise
    if args.no_solve and not args.suite and episodes > 1 and init_noise > 0 and (
            not args.no_score or args.target_ratio is not None):  # (it failed after episode 0, naming no option)
        raise ValueError(f"no shipped or cached optimum holds the perturbed starts of episodes 1..{episodes - 1} "
                         f"(--init-noise {init_noise:g}), and --no-solve solves none: give --init-noise 0 or "
                         "--episodes 1, or leave --no-solve out")
    if args.suite and args.sample is None and load_suite(args.suite).sampler:  # (the error named no option)
        raise ValueError(f"--suite {args.suite} draws its scenarios: give --sample N, the number of draws, in "
                         f"[1, {MAX_SAMPLE}]")
    scenarios = list(load_suite(args.suite).spread(braking, args.sample)) if args.suite else None
    _check_target_reachable(args.target_time, scenarios or [scenario or Scenario.nominal(braking)])
    # an unwritable --out fails now, not after the episodes; and after the other options, as its check may create
    # its folder (a bad --cache or --scenario left an empty one behind)
    out = _result_file(args)
    targeted = args.target_time is not None or args.target_ratio is not None
    if out is not None:
        check_not_an_input(out, controller_files(args.controller, braking, args.model, targeted=targeted), "--out")
    if scenarios and args.sample and args.sample > len(scenarios):
        log.warning(f"--sample {args.sample}: the {args.suite} suite has {len(scenarios)} {braking} scenarios; all of them run")
    controller = load_controller(args.controller, braking, args.model, trust_pickle=args.trust_pickle,
                                 scenario=scenario or (scenarios[0] if scenarios else None), targeted=targeted)
    if args.controller.strip() == "ppo" and args.model is None and not targeted and (
            scenarios or (scenario is not None and scenario != Scenario.nominal(braking))):
        log.warning(f"the shipped ppo_{braking} knows the paper's nominal cycle only; on other scenarios use the "
                    "target-conditioned policy (--target-ratio R or --target-time T) or --controller bc")
    from agents.ppo_config import TARGETED_ENV_IDS

    if not targeted and getattr(controller, "env_id", None) in TARGETED_ENV_IDS:  # (its env then draws the targets)
        log.warning(f"{args.controller} drives to a target cycle time: without --target-ratio R or --target-time T "
                    "each episode's is drawn at random in 1-2.5 T_min (recorded as its target_time)")
    what = f"{len(scenarios)} scenario(s) of the {args.suite} suite" if scenarios else f"{episodes} episode(s)"
    log.info(f"evaluating {args.controller} with {braking} braking: {what} ...")
    with _stdout_for_the_result(out):
        r = evaluate_controller(controller, braking, episodes=episodes, init_noise=init_noise,
                                seed=args.seed, score=not args.no_score, cache=args.cache, progress=log.info,
                                name=args.controller, act_timeout=args.act_timeout, scenario=scenario,
                                scenarios=scenarios, solve=not args.no_solve, target_time=args.target_time,
                                target_ratio=args.target_ratio)
    # (the options that chose the episodes and their targets, recorded: a file of --target-ratio 1.15 did not say so)
    r = {"controller": args.controller, "model": args.model, "suite": args.suite, "sample": args.sample,
         "target_time": args.target_time, "target_ratio": args.target_ratio, "aggregate": aggregate(r), **r}
    _put_result(r, out, summary_line(r, args.controller))
    return 0


def _train_cmd(args: argparse.Namespace) -> int:
    from agents.ppo_config import PPOConfig
    from agents.train_cli import run_train
    from wl_env.atomic_io import missing_folders

    for folder in (args.log_dir or PPOConfig.log_dir, args.cache):  # (created by run_train's checks, if missing)
        if folder and str(folder).strip():
            _CREATED.extend(reversed(missing_folders(folder)))
    return run_train(args, command="wl " + shlex.join(args.argv), prog="wl train")


def _run_cmd(args: argparse.Namespace) -> int:
    from wl.report import run_all

    if args.cache is not None:  # (before --out, whose check creates its folder)
        _out_dir(args.cache, "--cache")
    out = _out_dir(args.out)
    # every file it writes, checked now: a folder at results.json or pareto.png failed after 5-10 min of work
    from wl.report import BRAKINGS, RESULTS_FILE, check_report_files, report_files
    from wl_env.atomic_io import check_output_file

    check_output_file(out / RESULTS_FILE, "--out's results file")
    check_report_files(out, report_files(BRAKINGS, True), (out / RESULTS_FILE,))
    run_all(args.out, cache=args.cache, full_suite=args.full_suite)
    print((Path(args.out) / "leaderboard.md").read_text())
    return 0


def _report_cmd(args: argparse.Namespace) -> int:
    from wl.report import load_results, render

    if not args.results.strip():  # (Path("") is the working folder)
        raise ValueError("--results must name the folder of `wl run`'s results.json, got an empty string")
    results = load_results(args.results)
    if args.out is not None and not args.out.strip():  # (an empty --out wrote into --results without a word)
        raise ValueError("--out must name a folder, got an empty string (leave it out to write into --results)")
    out = _out_dir(args.out or args.results, "--out" if args.out else "--results")
    written = render(results, out, inputs=(Path(args.results) / "results.json",))
    print(f"report rebuilt from {Path(args.results) / 'results.json'}: {', '.join(str(p) for p in written)}")
    return 0


def _number(text: str, kind: type) -> Any:
    try:
        return kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {'an integer' if kind is int else 'a number'}, got {text!r}") from None


def _int_in(lo: int, hi: int) -> Callable[[str], int]:
    """An argparse type: an integer in [lo, hi]."""
    def parse(text: str) -> int:
        value = _number(text, int)
        if not lo <= value <= hi:
            raise argparse.ArgumentTypeError(f"must be an integer in [{lo}, {hi}], got {value}")
        return value
    return parse


def _float_in(lo: float, hi: float, open_lo: bool = False, open_hi: bool = False,
              unit: str = "") -> Callable[[str], float]:
    """An argparse type: a finite number in the interval lo..hi (ends open as asked; NaN and inf never pass)."""
    interval = f"{'(' if open_lo else '['}{lo:g}, {hi:g}{')' if open_hi else ']'}{unit}"

    def parse(text: str) -> float:
        value = _number(text, float)
        inside = math.isfinite(value) and (lo < value if open_lo else lo <= value) and (
            value < hi if open_hi else value <= hi)
        if not inside:
            raise argparse.ArgumentTypeError(f"must be a finite number in {interval}, got {text}")
        return value
    return parse


def _positive_int(text: str) -> int:
    value = _number(text, int)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def _mpc_fuel_weight(text: str) -> float:
    """The MPC's weighted mode's fuel weight: 0, or in [MIN_W_FUEL, 1] (a smaller one prices a step past a float)."""
    from mpc.controller.mpc import MIN_W_FUEL

    value = _unit_float(text)
    if 0.0 < value < MIN_W_FUEL:
        raise argparse.ArgumentTypeError(f"must be 0 (minimum time) or in [{MIN_W_FUEL:g}, 1], got {value:g}")
    return value


def _deadline_ms(text: str) -> float:
    """The MPC's deadline per step: in (0, 100] ms (the control interval), at least MIN_DEADLINE_MS (1e-4 was
    refused as MPCConfig's deadline_ms, naming no option)."""
    from mpc.controller.mpc import MIN_DEADLINE_MS

    value = _float_in(0, 100, open_lo=True, unit=" ms")(text)
    if value < MIN_DEADLINE_MS:
        raise argparse.ArgumentTypeError(f"must be a finite number in (0, 100] ms, at least {MIN_DEADLINE_MS:g} ms "
                                         f"(1 µs), got {text}")
    return value


def _unit_float(text: str) -> float:
    value = _number(text, float)
    if not 0.0 <= value <= 1.0:  # false for NaN too
        raise argparse.ArgumentTypeError(f"must lie in [0, 1], got {text}")
    return value


def _act_timeout(text: str) -> float:
    from agents.evaluate import MAX_ACT_TIMEOUT

    value = _number(text, float)
    if not 0.0 < value <= MAX_ACT_TIMEOUT:  # (false for NaN)
        raise argparse.ArgumentTypeError(f"must be a number of seconds in (0, {MAX_ACT_TIMEOUT:g}], got {text}")
    return value


def _seed(text: str) -> int:
    value = _number(text, int)
    from agents.ppo_config import MAX_SEED

    if not 0 <= value <= MAX_SEED:  # (a 4300-digit seed failed after the episodes, naming no option)
        raise argparse.ArgumentTypeError(f"must be an integer in [0, {MAX_SEED}]" + (f", got {value}" if value < 0 else ""))
    return value


def _json_option(text: str, option: str) -> Any:
    from wl_env.scenario import DuplicateKey, no_duplicate_keys

    try:
        return json.loads(text, object_pairs_hook=no_duplicate_keys)
    except DuplicateKey as exc:  # (json kept the last value without a word; --scenario refused it)
        raise ValueError(f"{option}: the field {exc.args[0]!r} is given twice") from None
    except ValueError as exc:  # (JSONDecodeError, and an integer of more digits than Python converts)
        raise ValueError(f"{option} is not valid JSON ({' '.join(str(exc).split())[:200]})") from None
    except RecursionError:  # (a RuntimeError, not a JSONDecodeError)
        raise ValueError(f"{option} is not valid JSON (nested too deeply)") from None


def _params_overrides(args: argparse.Namespace) -> Any:
    """The --params JSON as given (None if absent); ValueError naming it if it is empty or not JSON."""
    text = getattr(args, "params", None)
    if text is None:
        return None
    if not text.strip():
        raise ValueError("--params is empty: give a JSON object of LoaderParams fields")
    value = _json_option(text, "--params")
    if not isinstance(value, dict):  # (null was taken as no overrides; `wl params --set null` refuses it)
        raise ValueError(f"--params must be a JSON object of LoaderParams fields, got {type(value).__name__}")
    return value


def _params_from(args: argparse.Namespace):
    from wl_env.params import LoaderParams

    overrides = _params_overrides(args)
    try:
        return None if overrides is None else LoaderParams.from_dict(overrides)
    except ValueError as exc:  # (it named LoaderParams.M_load, not the option that set it)
        raise ValueError(f"--params: {exc}") from None


def _scenario_from(args: argparse.Namespace, braking_given: bool | None = None):
    """The --scenario (JSON text or a JSON file; a missing field is nominal, the braking --braking's), or None."""
    from wl_env.params import scenario_overrides
    from wl_env.scenario import Scenario

    if getattr(args, "scenario", None) is None:
        return None
    if not args.scenario.strip():
        raise ValueError("--scenario is empty: give a JSON object or a JSON file")
    try:  # (it reads a file of at most wl_env.scenario.MAX_SCENARIO_FILE_BYTES, a regular one)
        s = Scenario.parse(args.scenario)
    except ValueError as exc:
        raise ValueError(str(exc) if str(exc).startswith("--scenario") else f"--scenario: {exc}") from None
    overridden = scenario_overrides(_params_overrides(args))
    if overridden:  # (the scenario sets them: the --params values would be dropped without a word)
        raise ValueError(f"--params sets {', '.join(overridden)}, which the --scenario sets: give them in the scenario")
    given = args.braking is not None if braking_given is None else braking_given
    if given:
        named = _scenario_braking(args)
        if named is not None and named != args.braking:
            raise ValueError(f"--braking {args.braking} contradicts the --scenario's braking {named!r}")
        s = s.replace(braking=args.braking)
    return s


def _scenario_braking(args: argparse.Namespace) -> str | None:
    """The braking the --scenario names itself (None: it names none; its braking is then --braking's or the default)."""
    from wl_env.scenario import read_scenario_file

    text = args.scenario.strip()  # (Scenario.parse read it: it is valid)
    data = json.loads(text if text.startswith("{") else read_scenario_file(Path(text), "--scenario"))
    return data.get("braking")


def _suite_cmd(args: argparse.Namespace) -> int:
    from mpc.benchmark.suite import check_shipped, solve_suite

    ray = args.ray
    if ray is not None and args.workers is not None:  # (the Ray tasks took no notice of it, without a word)
        raise ValueError("--workers sets the local processes; with --ray the cluster runs the solves: give one of them")
    if args.cache is not None:
        _out_dir(args.cache, "--cache")
    if args.check and args.out is not None:  # (it compares with the shipped optima and writes no suite file)
        raise ValueError("--out names the suite file a solve writes; --check writes none: leave --out out")
    if args.check:
        rows = check_shipped(args.suite, cache=args.cache, limit=args.limit, workers=args.workers, ray_address=ray)
        bad = [r for r in rows if not r["ok"]]
        for r in rows:
            print(f"{r['key']}: " + ("OK" if r["ok"] else "MISMATCH") + (
                f" (fresh against shipped: T_min {100 * r['T_min_rel']:+.3f} %, fuel {100 * r['fuel_rel_min']:+.3f}.."
                f"{100 * r['fuel_rel_max']:+.3f} %)" if "T_min_rel" in r
                else f" ({r.get('problem')})"))
        # (with --cache, the solves it holds count: say so, not "a fresh solve")
        against = "a fresh solve" if args.cache is None else f"the solves in --cache {args.cache} (cached ones included)"
        print(f"{len(rows) - len(bad)} of {len(rows)} shipped optima agree with {against}")
        return 1 if bad else 0
    out = _out_file(args.out) if args.out is not None else None  # (an empty --out is an error, not the default)
    r = solve_suite(args.suite, cache=args.cache, out=out, workers=args.workers, ray_address=ray, limit=args.limit)
    import statistics

    per = r.per_scenario_s
    print(f"suite {r.suite}: {len(r.entries)} scenarios, {r.solved} solved now in {r.wall_time:.0f} s"
          + (f" (per scenario and braking alternative: median {statistics.median(per):.1f} s)" if per else "")
          + f" -> {r.file}")
    for key, why in r.failed.items():
        print(f"  no optimum for {key}: {why}")
    return 1 if r.failed else 0


def build_parser() -> argparse.ArgumentParser:
    from mpc.workers import max_local_workers
    from wl_env.suites import MAX_SAMPLE

    parser = _Parser(
        prog="wl",
        description="wheel-loader-gym: the wheel loader short loading cycle as a Gymnasium environment, "
        "its optimal control benchmark, and controllers scored against it.",
    )
    parser.add_argument("--version", action="store_true", help="print the version and exit")
    parser.add_argument("-v", "--verbose", action="store_true",
                        help="also log each solver call (debug lines on stderr): where a slow run spends its time")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    p = sub.add_parser("params", help="print the model parameters with units and provenance")
    p.add_argument("--json", action="store_true", help="print as JSON")
    p.add_argument("--set", metavar="JSON", help='overrides, e.g. \'{"M_load": 12000}\' (validated)')
    p.set_defaults(func=_params_cmd)

    scenario_help = ("the cycle: a Scenario as JSON text or a JSON file, e.g. '{\"payload\": 12000, "
                     "\"reverse_distance\": 5}' (a missing field is nominal; fields and ranges: wl_env.scenario)")
    p = sub.add_parser("ocp", help="solve the cycle's optimal control problem (the benchmark)")
    p.add_argument("--braking", choices=["service", "tc"], help="default: the scenario's, else service")
    p.add_argument("--scenario", metavar="JSON|FILE", help=scenario_help)
    p.add_argument("--objective", choices=["time", "fuel", "weighted"], default="time")
    p.add_argument("--time", type=float, metavar="T", help="fixed cycle time (s) for --objective fuel, in [0.4, 60] "
                   "(each phase is bounded to 30 s; the fuel-optimal cycle takes about 21.5 s)")
    p.add_argument("--w-fuel", type=_unit_float, metavar="W", help="fuel weight W1 in [0, 1] for --objective weighted")
    p.add_argument("--hessian", choices=["exact", "limited-memory"], help="IPOPT's Hessian (default exact)")
    p.add_argument("--params", metavar="JSON", help="parameter overrides as JSON")
    p.add_argument("--out", required=True, metavar="FILE.json", help="where to write the result")
    p.set_defaults(func=_ocp_cmd)

    p = sub.add_parser("pareto", help="the fuel-time Pareto front (cached)")
    p.add_argument("--braking", choices=["service", "tc", "both"], help="default: the scenario's, else both")
    p.add_argument("--scenario", metavar="JSON|FILE", help=scenario_help)
    p.add_argument("--points", type=_int_in(3, 100), default=11, help="cycle times on the front, 3..100 (default 11)")
    p.add_argument("--params", metavar="JSON", help="parameter overrides as JSON")
    p.add_argument("--cache", metavar="DIR", help="cache folder (default $WL_CACHE_DIR or ~/.cache/wheel-loader-gym)")
    p.add_argument("--no-cache", action="store_true", help="solve again even if cached")
    p.add_argument("--out", required=True, metavar="DIR", help="folder for pareto_<braking>.json")
    p.set_defaults(func=_pareto_cmd)

    p = sub.add_parser("mpc", help="drive the cycle with the receding-horizon MPC and score it")
    p.add_argument("--braking", choices=["service", "tc"], help="default: the scenario's, else service")
    p.add_argument("--scenario", metavar="JSON|FILE", help=scenario_help)
    p.add_argument("--mismatch", action="store_true", help="plan the --scenario's cycle with the nominal payload and "
                   "rolling resistance (the plant has the scenario's): the estimator learns the difference")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--min-time", action="store_true", help="minimum cycle time (default)")
    g.add_argument("--target-time", type=_float_in(1, 40, open_hi=True, unit=" s"), metavar="T",
                   help="minimum fuel, finishing by T seconds, in [1, 40) (the episode ends at 40 s)")
    g.add_argument("--w-fuel", type=_mpc_fuel_weight, metavar="W",
                   help="weighted fuel/time objective, fuel weight W: 0 (minimum time) or in [1e-06, 1]")
    p.add_argument("--deadline-ms", type=_deadline_ms, metavar="MS",
                   help="hard deadline per step in (0, 100] ms: a later solve gives way to the shifted previous plan")
    p.add_argument("--realtime", action="store_true", help="real-time MPC: each step applies the plan solved while "
                   "the steps before ran and hands its own solve to a worker thread (a control in about 0.1 ms)")
    h = p.add_mutually_exclusive_group()
    h.add_argument("--horizon-steps", type=_int_in(2, 1000), metavar="N",
                   help="a short receding horizon of N steps in [2, 1000], the rest of the cycle priced by the full "
                   "plan's value (default: 10; the full horizon with --realtime or --deadline-ms)")
    h.add_argument("--full-horizon", action="store_true", help="solve the whole rest of the cycle every step "
                   "(IPOPT; the default with --realtime and --deadline-ms)")
    p.add_argument("--horizon-solver", choices=["ipopt", "sqp-rti"],
                   help="the short horizons' solver: one real-time SQP iteration per step (sqp-rti, the default: hpipm, "
                   "IPOPT where it fails and for the full plans), or IPOPT")
    lag = p.add_mutually_exclusive_group()
    lag.add_argument("--replan-lag-steps", type=_int_in(1, 100), metavar="N",
                     help="a short horizon's re-plans (the plant estimate moved) run beside it on a worker thread and "
                     "take over N steps later, N in [1, 100] (default: 5)")
    lag.add_argument("--replan-in-step", action="store_true", help="a short horizon's re-plans in the step that needs "
                     "one (0.2-0.5 s steps), not beside it")
    p.add_argument("--no-safety-filter", action="store_true", help="apply the plans' controls as they are (default: "
                   "a control whose next step the model predicts over the deceleration or speed limit is eased)")
    p.add_argument("--rate-weight", type=_float_in(0, 1e6, unit=""), nargs=2, metavar=("W_MF", "W_AB"),
                   help="control-rate penalty on U_mf and U_ab (default: MPCConfig's, 0.1 0.1)")
    p.add_argument("--params", metavar="JSON", help="parameter overrides (the MPC's model and the plant)")
    p.add_argument("--payload-scale", type=_float_in(0, 10), default=1.0,
                   help="plant payload / model payload, in [0, 10] (mismatch study)")
    p.add_argument("--rolling-scale", type=_float_in(0, 10), default=1.0,
                   help="plant rolling resistance / model's, in [0, 10]")
    p.add_argument("--cache", metavar="DIR", help="cache folder of the Pareto fronts the score reads (default "
                   "$WL_CACHE_DIR or ~/.cache/wheel-loader-gym); a front not cached there is solved first")
    p.add_argument("--no-score", action="store_true", help="skip the score against the OCP (no Pareto front needed)")
    p.add_argument("--out", metavar="FILE.json", help="where to write the result (default, or -: the JSON to "
                   "stdout, the summary line to stderr)")
    p.set_defaults(func=_mpc_cmd)

    p = sub.add_parser("evaluate", help="run a controller for some episodes and score it against the optimum",
                       description="Run a controller in WheelLoader-v2 (or its own env) and score it against the "
                       "optimal control benchmark. Episode 0 starts at the nominal state (the one the optimum is computed for), "
                       "episodes 1..N-1 perturbed by --init-noise, episode i seeded SEED + i. Per episode and "
                       "aggregated: success (cycle completed, end targets met), cycle time, fuel, constraint "
                       "violation, time gap to the minimum cycle time and fuel gap to the Pareto fuel at the "
                       "same cycle time.")
    p.add_argument("--controller", required=True, metavar="{ppo,plan,bc,operator,mpc,module:Class}",
                   help="a built-in controller (ppo: with a target, the target-conditioned policy; plan: the "
                   "target-conditioned policy of one plan per cycle, WheelLoaderPlan-v1/-v0; bc: the behaviour-cloned MPC), or your class as module:Class or path/to/file.py:Class "
                   "(called with braking= if it takes it; needs act(obs) -> action, optionally reset())")
    p.add_argument("--braking", choices=["service", "tc"], help="default: the scenario's, else service")
    p.add_argument("--scenario", metavar="JSON|FILE", help=scenario_help)
    p.add_argument("--suite", choices=["nominal", "train", "test", "corners"],
                   help="one episode per scenario of the suite (of the braking alternative), from its own start")
    p.add_argument("--sample", type=_int_in(1, MAX_SAMPLE), metavar="N", help=f"with --suite: N scenarios in [1, "
                   f"{MAX_SAMPLE}] spread evenly over it (a sampler suite: N draws)")
    p.add_argument("--no-solve", action="store_true", help="score only against shipped or cached optima (an "
                   "episode of another cycle is an error instead of a solve)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--target-time", type=_float_in(1, 40, open_hi=True, unit=" s"), metavar="T",
                   help="each episode's target cycle time, in [1, 40) s (the controller's reset takes target_time)")
    g.add_argument("--target-ratio", type=_float_in(1, 3, unit=" (times T_min)"), metavar="R",
                   help="each episode's target: R times its own minimum cycle time, R in [1, 3]")
    p.add_argument("--model", metavar="PATH", help="ppo, bc: the policy, PATH.safetensors with PATH_vecnormalize.npz and "
                   "PATH.json beside it, or a run folder (default agents/policies/ppo_<braking>, with a target "
                   "ppo_target_<braking>; bc: bc_target_<braking>); module:Class: passed as model=")
    p.add_argument("--trust-pickle", action="store_true", help="ppo: also load a stable-baselines3 .zip (+ .pkl), "
                   "which unpickles and can run code: for trusted input only, e.g. your own training runs")
    p.add_argument("--episodes", type=_int_in(1, 100_000), metavar="N",
                   help="episodes, 1..100000 (default 10; not with --suite: one per scenario)")
    p.add_argument("--init-noise", type=_unit_float, metavar="X",
                   help="start-state perturbation of episodes 1..N-1, 0..1 (default 1.0; not with --suite)")
    p.add_argument("--seed", type=_seed, default=0, metavar="S", help="seed of episode 0; episode i uses S + i")
    p.add_argument("--cache", metavar="DIR", help="cache folder of the Pareto fronts (default $WL_CACHE_DIR or "
                   "~/.cache/wheel-loader-gym); a front not cached there is solved first (minutes)")
    p.add_argument("--no-score", action="store_true", help="skip the score against the OCP (no Pareto front needed)")
    p.add_argument("--act-timeout", type=_act_timeout, metavar="SECONDS", help="fail if one act() call takes longer, "
                   "in (0, 86400] (default: off, no limit; a SIGALRM timer: it interrupts Python code, not a hung C call)")
    p.add_argument("--out", metavar="FILE.json", help="where to write the evaluation (default, or -: the JSON to "
                   "stdout, the summary line to stderr)")
    p.set_defaults(func=_evaluate_cmd)

    from agents.train_cli import add_train_args, ray_address, refuse_repeated_options

    p = sub.add_parser("train", help="train a PPO policy (stable-baselines3 on the native vector env)",
                       description="Train a PPO policy for WheelLoader-v1; every field of agents.ppo.PPOConfig is a "
                       "flag. A run lives in <log-dir>/<run-name>/ (config.json, tb/, eval.csv, checkpoints/, "
                       "final/); --resume continues it from its newest checkpoint, --export PATH ships the final "
                       "policy pickle-free as PATH.safetensors + PATH_vecnormalize.npz + PATH.json.")
    add_train_args(p)
    p.set_defaults(func=_train_cmd)

    p = sub.add_parser("suite", help="a suite's reference optima: solve (resumable) or check the shipped ones")
    suite_sub = p.add_subparsers(dest="suite_command", metavar="ACTION", required=True)
    q = suite_sub.add_parser("solve", help="T_min and the Pareto front of every scenario of a suite")
    q.add_argument("--suite", required=True, choices=["nominal", "test", "corners"])
    q.add_argument("--check", action="store_true", help="solve afresh and compare with the shipped optima "
                   "(exit 1 where a fresh solve beats one: T_min lower by over 0.1 %%, or the fuel at a shipped "
                   "point by over 0.3 %%)")
    q.add_argument("--ray", nargs="?", const="local", type=ray_address, metavar="ADDRESS", help="run on a Ray cluster (ADDRESS, e.g. "
                   "ray://host:10001, or none: a Ray instance on this machine); default: local processes")
    q.add_argument("--workers", type=_int_in(1, max_local_workers()), metavar="N",
                   help=f"local processes, at most {max_local_workers()} (default: the CPU count)")
    q.add_argument("--limit", type=_positive_int, metavar="N", help="only N scenarios per braking alternative")
    q.add_argument("--cache", metavar="DIR", help="cache folder (default $WL_CACHE_DIR or ~/.cache/wheel-loader-gym)")
    q.add_argument("--out", metavar="FILE.json", help="the suite's optima file (default <cache>/suites/<suite>.json)")
    q.set_defaults(func=_suite_cmd)

    p = sub.add_parser("run", help="the main job: benchmark, every controller, report (results/)")
    p.add_argument("--out", default="results", metavar="DIR", help="report folder (default results/)")
    p.add_argument("--cache", metavar="DIR", help="cache folder for solved optima")
    p.add_argument("--full-suite", action="store_true", help="run the controllers on every scenario of the test suite "
                   "(default: a fixed sample of 10 per braking alternative)")
    p.set_defaults(func=_run_cmd)

    p = sub.add_parser("report", help="rebuild the report of `wl run` from its results.json (nothing is solved or run)")
    p.add_argument("--results", required=True, metavar="DIR", help="the folder holding results.json")
    p.add_argument("--out", metavar="DIR", help="where to write the report (default: the --results folder)")
    p.set_defaults(func=_report_cmd)
    refuse_repeated_options(parser)
    return parser


MAX_ERROR_CHARS = 2000  # an error quoting a user's 10 MB of JSON stays a readable line


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= MAX_ERROR_CHARS else text[:MAX_ERROR_CHARS] + " ..."


def main(argv: list[str] | None = None) -> int:
    """Run the ``wl`` command line ``argv``; returns the exit code (0, 1 for a run that did not complete,
    2 for a user error, 130 for an interrupt, 143 for SIGTERM).

    Called as the program (``argv`` None: ``wl``, ``python -m wl``), an interrupt ends the process at once
    with exit code 130: the outputs are atomic and the workers already stopped, and the interpreter's
    teardown (0.4 s with torch and CasADi loaded) only delays the exit Ctrl-C asked for. ``wl train``
    exits normally (its progress bar and TensorBoard writer clean up at exit).
    """
    as_program = argv is None
    argv = list(sys.argv[1:] if argv is None else argv)
    from mpc import interrupt  # (signal and threading only: in place before the packages' imports)

    # The flag-setting handler from the start: Ctrl-C inside numpy's import came out as an ImportError with no
    # KeyboardInterrupt in its chain (a traceback, exit 1), which only the flag tells from a broken install; and
    # Ctrl-C between the parse and the command's own handler was a KeyboardInterrupt's traceback.
    with interrupt.handling():
        try:
            code, command = _main(argv)
        except KeyboardInterrupt:  # (between the steps: nothing written yet)
            _remove_empty_created()
            print("wl: interrupted", file=sys.stderr)
            code, command = interrupt.exit_code(), None
    if code in (130, 143) and as_program and command != "train":
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    return code


def _main(argv: list[str]) -> tuple[int, str | None]:
    """:func:`main`'s work under the interrupt handler: the exit code and the subcommand."""
    from mpc import interrupt

    try:
        parser = build_parser()  # (it imports the packages: 0.3-1 s in which Ctrl-C printed a traceback)
        args = parser.parse_args(argv)
        interrupt.check()  # (one that a C extension's import swallowed: the flag says it came)
    except (KeyboardInterrupt, ImportError) as exc:  # (ImportError: Ctrl-C inside numpy's import, "PyCapsule_Import ...")
        if not interrupt.caused_by_interrupt(exc):
            raise
        print("wl: interrupted", file=sys.stderr)
        return interrupt.exit_code(), None
    except UsageError as exc:
        print(f"wl: error: {_one_line(exc)}", file=sys.stderr)
        return 2, None
    except SystemExit as exc:  # --help: return its code instead of leaving the caller (tests, scripts)
        return (exc.code if isinstance(exc.code, int) else 0), None
    args.argv = argv  # the command line as given, recorded by `wl train`
    if args.version:
        import wl_env

        print(wl_env.__version__)
        return 0, None
    if not getattr(args, "func", None):
        parser.print_help()
        return 0, None
    _CREATED.clear()
    try:  # the environment's settings, read at the first NLP build or cache write: checked before any work
        _check_environment()
    except ValueError as exc:
        _remove_empty_created()
        print(f"wl: error: {_one_line(exc)}", file=sys.stderr)
        return 2, None
    # A Ctrl-C whose KeyboardInterrupt an import swallowed (numpy's scalar types registered with `abc` from C) was lost
    # for good here, as the command's handler clears the flag: `wl pareto` then waited for its workers' fronts
    interrupt.check()
    return _run_command(args), args.command


def _check_environment() -> None:
    """$WL_CODEGEN, $WL_NLP_CACHE_SIZE, and the folders $WL_CACHE_DIR and $WL_CODEGEN_DIR (probed by a write), each
    a ValueError naming the variable (a $WL_CACHE_DIR that was a file failed after an episode, naming no variable)."""
    from wl_env.atomic_io import check_output_folder

    if os.environ.get("WL_CODEGEN") is not None:
        from mpc.controller import codegen

        shared = codegen.shared_library_folder() if codegen.mode() == "on" else ""
        if shared:  # (it failed after ~1.5 s of work)
            raise ValueError(f"$WL_CODEGEN=on: {shared}")
    if os.environ.get("WL_NLP_CACHE_SIZE") is not None:
        from mpc.benchmark.ocp import nlp_cache_size

        nlp_cache_size()
    for name in ("WL_CACHE_DIR", "WL_CODEGEN_DIR"):
        if os.environ.get(name):  # (a folder created here is removed again if the command stops and leaves it empty)
            _created_by(lambda name=name: check_output_folder(os.environ[name], f"${name}"), Path(os.environ[name]))


def _run_command(args: argparse.Namespace) -> int:
    """``args.func(args)`` with logging to stderr and the interrupt handler in place; the exit code."""
    from mpc import interrupt
    from wl_env.logs import cli_logging

    level = logging.DEBUG if args.verbose else logging.INFO
    with cli_logging(level), interrupt.handling():  # Ctrl-C ends a solve instead of failing one start of it
        try:
            code = int(args.func(args) or 0)
            if code in (130, 143):  # (`wl train` returns its interrupt: it left an empty --log-dir behind)
                _remove_empty_created()
            _CREATED.clear()
            return code
        # (LookupError: an optimum --no-solve may not solve; SystemError: Ctrl-C inside CasADi's DM.__array__,
        # "returned a result with an exception set")
        except (KeyboardInterrupt, ValueError, LookupError, RuntimeError, OSError, SystemError, ImportError) as exc:
            _remove_empty_created()
            if interrupt.caused_by_interrupt(exc):  # (also an interrupt a library turned into an error)
                print("wl: interrupted", file=sys.stderr)
                return interrupt.exit_code()
            if isinstance(exc, (SystemError, ImportError)):  # (ImportError: a command's late import, as in main)
                raise
            print(f"wl: error: {_one_line(exc)}", file=sys.stderr)
            return 2


if __name__ == "__main__":
    sys.exit(main())
