"""Which of several target-conditioned policies to ship, chosen on the training distribution (never on `test`).

    python scripts/select_policy.py --braking service --policies runs/a/final/policy.safetensors runs/b/...

The rule of stops 42-44 (docs/benchmarks.md section 7): each policy drives the same ``--draws`` fresh draws of
the ``train`` suite (``--seed``) at the three targets of the leaderboard (1, 1.15 and 1.5 times each draw's
estimated T_min); the least fuel summed over the three targets, per draw, wins among the policies that keep
every limit. Printed per policy: that fuel, the successes and the episodes over a limit. ``--json`` writes the
records (atomically).

``--by gap`` ranks by #14's own figures instead: each episode scored against its draw's optimum at the cycle time
it reached (solved per episode, the draws' minimum times kept in ``--cache``), the least sum over the three
targets of the median fuel gap and the median lateness wins. Fuel in grams is blind to time: at the fastest
target a later cycle burns less, so the grams rule preferred the policy 1.3 points later there (stop 56).
"""

from __future__ import annotations

import logging
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # (this checkout's packages, not an installed copy)
from agents.evaluate import policy_input_files  # noqa: E402
from agents.ppo_config import TARGETED_ENV_IDS  # noqa: E402
from agents.train_cli import refuse_repeated_values, tyro_options  # noqa: E402
from wl.report import TARGETS  # noqa: E402
from wl_env.atomic_io import check_not_an_input, check_output_file, check_output_folder, write_json_atomic  # noqa: E402
from wl_env.cycle import check_braking  # noqa: E402
from wl_env.logs import run_script  # noqa: E402

log = logging.getLogger("select_policy")
RATIOS = tuple(ratio for _, ratio in TARGETS)  # the leaderboard's targets, times T_min


@dataclass
class Options:
    braking: str = "service"
    policies: list[str] = field(default_factory=list)  # pickle-free policy files (PATH.safetensors)
    draws: int = 100  # fresh draws of the train suite
    seed: int = 7  # of the draws (stops 42-44: 7)
    json: str | None = None  # the records, written at the end
    by: str = "fuel"  # fuel: grams summed over the targets; gap: median fuel gap + median lateness per target
    cache: str | None = None  # with --by gap: a folder for the draws' optima (the same for every policy)


def check(o: Options) -> None:
    check_braking(o.braking)
    if not o.policies:
        raise ValueError("--policies needs at least one policy file")
    # (one record for the two: the others' counts stood beside it; also one policy by two spellings, ./P and P, or
    # P and P.safetensors: the file each loads from)
    from agents.ppo import policy_source

    refuse_repeated_values("--policies", o.policies, "a policy", key=policy_source)
    if not 1 <= o.draws <= 10_000:
        raise ValueError(f"--draws must be an integer in [1, 10000], got {o.draws}")
    if not 0 <= o.seed <= 2**32 - 1:
        raise ValueError(f"--seed must be an integer in [0, 2**32 - 1], got {o.seed}")
    if o.by not in ("fuel", "gap"):
        raise ValueError(f"--by must be 'fuel' or 'gap', got {o.by!r}")
    if o.cache is not None and o.by != "gap":
        raise ValueError("--cache keeps the optima of --by gap: not with --by fuel")
    if o.cache is not None and o.json is not None:  # (--cache X --json X: every episode, then "X is a folder")
        from wl_env.atomic_io import refuse_one_path_twice

        refuse_one_path_twice([("--cache", o.cache), ("--json", o.json)])
    if o.json is not None:
        check_output_file(o.json, "--json")
        for policy in o.policies:  # (--json P.json of --policies P wrote the records over the policy's metadata)
            check_not_an_input(o.json, policy_input_files(policy), "--json")
    if o.cache is not None:  # (with the other options, before the policies are read)
        check_output_folder(o.cache, f"--cache {o.cache}")


def run(o: Options) -> dict[str, Any]:
    check(o)
    from agents.evaluate import evaluate_controller, load_controller
    from wl_env.suites import load_suite

    suite, rng = load_suite("train"), np.random.default_rng(o.seed)
    draws = [suite.sample(rng, o.braking) for _ in range(o.draws)]
    records = []
    # every policy read and checked before any episode runs (a bad second one surfaced after the first's 300 episodes)
    controllers = {path: load_controller("ppo", o.braking, model=path) for path in o.policies}
    for path, controller in controllers.items():  # (a v1 policy failed "PPOPolicy.reset takes no target_time" after
        # the policies before it had driven every draw at every target)
        if controller.env_id not in TARGETED_ENV_IDS:
            raise ValueError(f"--policies {path} is a policy of {controller.env_id}, which is given no target cycle "
                             f"time: the policies compared drive to targets ({', '.join(TARGETED_ENV_IDS)})")
    for path, controller in controllers.items():
        fuel, successes, over, per_target = 0.0, 0, 0, {}
        for ratio in RATIOS:
            res = evaluate_controller(controller, o.braking, scenarios=draws, score=o.by == "gap", cache=o.cache,
                                      target_ratio=ratio, min_time="estimate")
            episodes = res["per_episode"]
            fuel += sum(e["fuel_g"] for e in episodes)
            successes += sum(bool(e["success"]) for e in episodes)
            over += sum(e["max_violation"] > 0.0 for e in episodes)
            if o.by == "gap":
                agg = res["summary"]
                per_target[str(ratio)] = {"fuel_gap_median": agg["fuel_gap_median"], "lateness_median": agg["lateness_median"]}
        rec = {"policy": path, "fuel_per_draw_g": fuel / o.draws, "successes": successes,
               "episodes": len(RATIOS) * o.draws, "over_a_limit": over}
        if o.by == "gap":
            rec["per_target"] = per_target
            # (a target with no scored episode, every cycle off its marks, has no median: None, and it ranks last)
            medians = [v for t in per_target.values() for v in (t["fuel_gap_median"], t["lateness_median"])]
            rec["gap_score_pct"] = None if None in medians else 100.0 * sum(medians)
        records.append(rec)
        log.info("%s: %.2f g per draw over the three targets, %d / %d on their marks, %d over a limit%s", path,
                 rec["fuel_per_draw_g"], successes, rec["episodes"], over,
                 "" if o.by == "fuel" else "; fuel gap + lateness medians summed over the targets " + (
                     "none (a target without a scored cycle)" if rec["gap_score_pct"] is None else f"{rec['gap_score_pct']:.2f} %"))
    keeping = [r for r in records if r["over_a_limit"] == 0]
    key = "fuel_per_draw_g" if o.by == "fuel" else "gap_score_pct"
    chosen = min(keeping, key=lambda r: math.inf if r[key] is None else r[key])["policy"] if keeping else None
    log.info("chosen: %s", chosen or "none (every policy went over a limit)")
    out = {"braking": o.braking, "draws": o.draws, "seed": o.seed, "by": o.by, "ratios": list(RATIOS), "records": records,
           "chosen": chosen}
    if o.json is not None:
        write_json_atomic(o.json, out)
    return out


if __name__ == "__main__":
    run_script("select_policy", lambda: run(tyro_options(Options)))
