"""The shipped PPO policies and the rule-based operator, scored against the optimum, both alternatives.

Each controller runs ``--episodes`` episodes through :func:`agents.evaluate.evaluate_controller` (the
evaluation of ``wl evaluate``): episode 0 from the nominal start, the others from starts perturbed with
``--init-noise``. The table gives the success rate over all episodes, the nominal episode's cycle time,
fuel and gaps (time gap to the minimum cycle time, fuel gap to the Pareto fuel at the same cycle time),
the mean gaps over the successful episodes, and for PPO the training wall time and steps recorded with
the shipped policy (``agents/policies/ppo_<braking>.json``). Usage::

    python scripts/bench_agents.py [--episodes 100] [--json PATH]
    python scripts/bench_agents.py --suite test [--mpc-sample 10] [--json PATH]

``--suite test``: every scenario of the held-out suite per braking alternative, each scored against its own
optimum (shipped: nothing is solved). The target-conditioned PPO and the behaviour-cloned MPC (imitation)
run at three targets per scenario (fastest, 1.15 and 1.5 T_min, :data:`wl.report.TARGETS`); the operator at
its own pace; the MPC in minimum-time mode and at the 1.15 and 1.5 targets, on ``--mpc-sample`` scenarios
spread over the suite (it takes 5-20 s a cycle). Printed per row: success, median and p90 of both gaps,
median lateness, largest violation. ``--suite test --runs RUN_DIR ...``: those runs' policies instead (e.g.
one per seed), with each metric's median and interquartile range over them.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from agents.evaluate import default_policy_path, evaluate_controller, load_controller, policy_input_files  # noqa: E402
from agents.train_cli import refuse_repeated_values  # noqa: E402
from mpc.benchmark.ocp import write_json_atomic  # noqa: E402
from mpc.benchmark.pareto import pareto_fronts  # noqa: E402
from wl.cli import _float_in, _int_in  # noqa: E402  (the command line's checked option types)


def pct(v: float | None) -> str:
    return "n/a" if v is None else f"{100 * v:+.1f} %"


def runs_mode(args: argparse.Namespace) -> None:
    """Each run's final policy on the suite at the three targets; the spread over the runs per braking and target."""
    from agents.ppo import load_policy
    from agents.seeds import quartiles
    from wl.report import collect_suite, suite_table

    policies = {run: load_policy(run) for run in args.runs}
    suite = collect_suite(args.suite, sample=None, controllers=lambda b: [], at_targets=lambda b: [
        (run, lambda p=p: p) for run, p in policies.items() if p.braking == b])
    print("\n".join(suite_table(suite)))
    keys = ("success_rate", "fuel_gap_median", "fuel_gap_p90", "time_gap_median", "lateness_median", "max_violation")
    spread = []
    for b in sorted({r["braking"] for r in suite["rows"]}):
        for target in dict.fromkeys(r["target"] for r in suite["rows"]):
            rows = [r for r in suite["rows"] if r["braking"] == b and r["target"] == target]
            spread.append({"braking": b, "target": target, "runs": len(rows),
                           **{k: quartiles([r[k] for r in rows]) for k in keys}})
    print("\n| braking | target | runs | " + " | ".join(keys) + " |\n|---|---|---|" + "---|" * len(keys))
    for line in spread:
        cells = ["-" if line[k] is None else f"{100 * line[k]['median']:.1f} ({100 * line[k]['q25']:.1f}-"
                 f"{100 * line[k]['q75']:.1f}) %" for k in keys]
        print(f"| {line['braking']} | {line['target']} | {line['runs']} | " + " | ".join(cells) + " |")
    if args.json:
        write_json_atomic(args.json, {"suite": args.suite, "runs": args.runs, "rows": suite["rows"], "spread": spread})


def suite_mode(args: argparse.Namespace) -> None:
    from mpc.controller.mpc import MPCController
    from wl.report import TARGETS, collect_suite, suite_table, target_controllers

    t0 = time.perf_counter()
    learned = collect_suite(args.suite, sample=None, controllers=lambda b: [
        ("operator", lambda: load_controller("operator", b))], at_targets=target_controllers)
    mpc = collect_suite(args.suite, sample=args.mpc_sample, controllers=lambda b: [
        ("mpc (min time)", lambda: load_controller("mpc", b))], at_targets=lambda b: [("mpc", lambda: MPCController(b))],
        targets=TARGETS[1:])
    for r in learned["rows"]:
        kind = {"ppo (target-conditioned)": "ppo-target", "ppo (plan)": "plan", "bc (imitation)": "bc"}.get(r["controller"])
        if kind:
            meta = json.loads(default_policy_path(r["braking"], kind).with_suffix(".json").read_text())
            r.update(training_wall_time_s=meta.get("training_wall_time_s"), num_timesteps=meta.get("num_timesteps"))
    rows = sorted(learned["rows"] + mpc["rows"], key=lambda r: (r["braking"], r["controller"]))
    print("\n".join(suite_table({**learned, "rows": rows})))
    print(f"\n{time.perf_counter() - t0:.0f} s")
    if args.json:
        write_json_atomic(args.json, {"suite": args.suite, "rows": rows, "episodes": learned["episodes"] + mpc["episodes"],
                                      "mpc_sample": args.mpc_sample, "wall_time_s": time.perf_counter() - t0})


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--episodes", type=_int_in(1, 100_000), help="episodes per controller (default 100; not with --suite)")
    ap.add_argument("--init-noise", type=_float_in(0, 1), help="start perturbation, 0..1 (default 1.0; not with --suite)")
    ap.add_argument("--seed", type=_int_in(0, 2**31 - 1), help="seed of episode 0 (default 10000; not with --suite)")
    ap.add_argument("--json", metavar="PATH", help="also write the raw numbers")
    ap.add_argument("--suite", choices=["test", "corners"], help="run the suite mode (see above)")
    ap.add_argument("--mpc-sample", type=_int_in(1, 1000), help="--suite: scenarios per braking the MPC runs (default 10)")
    ap.add_argument("--runs", nargs="+", metavar="RUN_DIR", help="--suite: instead, these runs' policies (e.g. one per "
                    "seed) at the three targets, and each metric's median and interquartile range over them")
    from agents.train_cli import refuse_repeated_options

    refuse_repeated_options(ap)  # (argparse kept the last of an option given twice, without a word)
    args = ap.parse_args()
    from wl_env.atomic_io import check_output_option

    check_output_option(ap, args.json, "--json")  # (now: it was written only at the end, after the work)
    if args.runs and not args.suite:
        ap.error("--runs needs --suite")
    # (each was ignored without a word where it does not apply)
    given = [flag for flag, value in (("--episodes", args.episodes), ("--init-noise", args.init_noise),
                                      ("--seed", args.seed)) if value is not None]
    if args.suite and given:
        ap.error(f"not with --suite (each scenario runs once from its own start): {', '.join(given)}, the nominal "
                 "mode's episodes")
    if args.mpc_sample is not None and (not args.suite or args.runs):
        ap.error("--mpc-sample sets the MPC's scenarios of --suite without --runs: leave it out")
    args.episodes = 100 if args.episodes is None else args.episodes
    args.init_noise = 1.0 if args.init_noise is None else args.init_noise
    args.seed = 10_000 if args.seed is None else args.seed
    args.mpc_sample = 10 if args.mpc_sample is None else args.mpc_sample
    try:  # (one run by two spellings, runs/a and runs/a/, or runs/a and runs/a/final: evaluated twice, counted twice)
        from agents.ppo import policy_source

        refuse_repeated_values("--runs", args.runs, "a run", key=policy_source)
    except ValueError as exc:
        ap.error(str(exc))
    if args.json and args.runs:  # (a run's policy file as --json was written over after the work)
        from wl_env.atomic_io import check_not_an_input

        try:
            check_not_an_input(args.json, [f for run in args.runs for f in policy_input_files(run)], "--json")
        except ValueError as exc:
            ap.error(str(exc))
    if args.suite:
        return runs_mode(args) if args.runs else suite_mode(args)
    fronts = pareto_fronts(progress=True)
    rows: list[dict[str, Any]] = []
    for braking in ("service", "tc"):
        for name in ("ppo", "operator"):
            print(f"[{braking}] {name}: {args.episodes} episodes", file=sys.stderr, flush=True)
            result = evaluate_controller(load_controller(name, braking), braking, episodes=args.episodes,
                                         init_noise=args.init_noise, seed=args.seed, front=fronts[braking])
            row = {"controller": name, "braking": braking, **result["summary"]}
            if name == "ppo":
                meta = json.loads(default_policy_path(braking).with_suffix(".json").read_text())
                row.update(training_wall_time_s=meta["training_wall_time_s"], num_timesteps=meta["num_timesteps"])
            rows.append(row)

    print("| controller | braking | success rate | nominal T (s) | nominal fuel (g) | nominal time gap | "
          "nominal fuel gap | mean time gap | mean fuel gap | max violation | training |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---|")
    for r in rows:
        nom = r["nominal"]
        train = (f"{r['training_wall_time_s'] / 60:.1f} min, {r['num_timesteps'] / 1e6:.1f} M steps"
                 if "training_wall_time_s" in r else "-")
        print(f"| {r['controller']} | {r['braking']} | {100 * r['success_rate']:.0f} % | {nom['T']:.2f} | "
              f"{nom['fuel_g']:.2f} | {pct(nom['time_gap'])} | {pct(nom['fuel_gap'])} | {pct(r['time_gap']['mean'])} | "
              f"{pct(r['fuel_gap']['mean'])} | {100 * r['max_violation']:.1f} % | {train} |")
    if args.json:
        write_json_atomic(args.json, {"rows": rows, "episodes": args.episodes, "init_noise": args.init_noise,
                                      "seed": args.seed})


if __name__ == "__main__":
    from wl_env.logs import PACKAGES, run_script

    run_script("bench_agents.py", main, PACKAGES)  # (the Pareto sweep's progress, as `wl` shows it; a missing run in one line)
