"""The MPC in its other settings on a suite's cycles: real time, a hard deadline, the full horizon, ... (stop 68).

    python scripts/bench_modes.py --braking tc --suite test --count 20 --settings realtime deadline --modes time 1.15
    python scripts/bench_modes.py --braking service --suite corners --count 14 --mismatch --settings default deadline

``bench_draws.py`` runs the default controller; a user may switch it to any of ``wl mpc``'s settings, and each has
its own first plan and steps. Each of ``--settings`` (names below: MPCConfig fields over the default's) runs the
``--count`` cycles of ``--suite`` from ``--first`` in each of ``--modes`` (``bench_draws.py``'s: ``time``, ``mismatch``
or a target ratio of the scenario's estimated T_min); ``--mismatch`` plans every run on the nominal payload and
rolling resistance (the plant the cycle's). Per run as ``bench_draws.py``: T, fuel, on the marks, the largest
violation, the target met, the first step's planning and the later steps' times; the summary per setting and mode.
Real time and the deadline make the runs depend on the machine's speed.
"""

from __future__ import annotations

import logging
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # (this checkout's packages, not an installed copy)
from agents.train_cli import refuse_repeated_values, tyro_options  # noqa: E402
from wl_env.atomic_io import check_output_file  # noqa: E402
from wl_env.cycle import check_braking  # noqa: E402
from wl_env.logs import run_script  # noqa: E402

log = logging.getLogger("bench_modes")

# each setting's MPCConfig fields over the default's (wl mpc's flags of the same names)
SETTINGS: dict[str, dict[str, Any]] = {
    "default": {},
    "realtime": {"realtime": True},
    "deadline": {"deadline_ms": 100.0},
    "full-horizon": {"horizon_steps": None},
    "horizon-ipopt": {"horizon_solver": "ipopt"},
    "replan-in-step": {"replan_lag_steps": None},
    "no-safety-filter": {"safety_filter": False},
    "no-rate-weight": {"rate_weight": (0.0, 0.0)},
}


@dataclass
class Options:
    braking: str = "tc"
    suite: str = "test"
    first: int = 0  # the suite's first cycle of this braking to run
    count: int = 6  # cycles from --first
    settings: tuple[str, ...] = ("realtime", "deadline")  # names of SETTINGS
    modes: tuple[str, ...] = ("time", "1.15")  # time, mismatch, or a target ratio of T_min (bench_draws.py's)
    mismatch: bool = False  # plan on the nominal payload and rolling resistance, the plant the cycle's
    out: str | None = None  # JSON of the per-run records and the summary


def check(o: Options) -> None:
    from bench_draws import target_ratio

    check_braking(o.braking)
    if not 0 <= o.first <= 10_000:
        raise ValueError(f"--first must be an integer in [0, 10000], got {o.first}")
    if not 1 <= o.count <= 1000:
        raise ValueError(f"--count must be an integer in [1, 1000], got {o.count}")
    if not o.settings or any(s not in SETTINGS for s in o.settings):
        raise ValueError(f"--settings must each be one of {sorted(SETTINGS)}, got {list(o.settings)}")
    if not o.modes:
        raise ValueError("--modes must name at least one mode")
    for mode in o.modes:
        target_ratio(mode)
    refuse_repeated_values("--settings", o.settings, "a setting")
    refuse_repeated_values("--modes", o.modes, "a mode", key=lambda m: m if m in ("time", "mismatch") else target_ratio(m))
    if o.out is not None:
        check_output_file(o.out, "--out")


def run(o: Options) -> dict[str, Any]:
    check(o)
    from bench_draws import run_one, summarize
    from bench_mpc import summary_line, write_with_speed

    from wl_env.suites import load_suite

    scenarios = load_suite(o.suite).of(o.braking)
    if o.first + o.count > len(scenarios):
        raise ValueError(f"--first {o.first} --count {o.count}: the {o.suite} suite has {len(scenarios)} {o.braking} "
                         "cycles")
    records, summary = [], {}
    for setting in o.settings:
        for mode in o.modes:
            runs = []
            for i in range(o.first, o.first + o.count):
                rec = {"setting": setting, "cycle": i, **run_one(o.braking, scenarios[i], mode, SETTINGS[setting], o.mismatch)}
                runs.append(rec)
                log.info("%s %s %s[%d]: %s", setting, mode, o.suite, i, rec.get("error") or
                         f"T {rec['T']:.1f} s, fuel {rec['fuel_g']:.2f} g, success {rec['success']}, violation "
                         f"{rec['max_violation']:.3g}, target met {rec['target_met']}, max step {rec['step_max_ms']:.0f} ms")
            records += runs
            summary[f"{setting} {mode}"] = summarize(runs)
            print(f"{o.braking} {setting} {mode}: {summary_line(summary[f'{setting} {mode}'])}")
    write_with_speed(o.out, o, summary, records)
    return summary


if __name__ == "__main__":
    run_script("bench_modes", lambda: run(tyro_options(Options)))
