"""Plot a PPO run's learning curve from its ``eval.csv`` (written by ``scripts/train_ppo.py``).

Four panels against training steps: success rate of the deterministic policy (perturbed starts and
the nominal start), return, cycle time and fuel of the nominal cycle with the optimum's references, and
the time and fuel gaps to the optimum with the 15 % target (a target-conditioned run: its episodes at
three targets, and the median fuel gap over them and the median lateness). Usage::

    python scripts/plot_learning_curve.py runs/ppo_service_s0 --out docs/learning_curve_service.png
    python scripts/plot_learning_curve.py docs/learning_curve_tc.csv --braking tc --out docs/learning_curve_tc.png
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from agents.ppo import EVAL_FIELDS, read_eval_csv  # noqa: E402
from wl_env.atomic_io import save_figure  # noqa: E402

GAP_TARGET = 0.15


def _series(rows: list[dict[str, float]], key: str) -> np.ndarray:
    return np.array([r.get(key, math.nan) for r in rows], dtype=float)


def plot(rows: list[dict[str, float]], braking: str, title: str, out: Path, front: object | None = None) -> Path:
    steps = _series(rows, "step") / 1e6
    fig, axes = plt.subplots(2, 2, figsize=(11, 7), sharex=True)
    ax = axes[0, 0]
    ax.plot(steps, _series(rows, "success_rate"), label="success rate (perturbed starts)")
    ax.plot(steps, _series(rows, "completion_rate"), "--", label="completion rate (perturbed starts)")
    ax.plot(steps, _series(rows, "nominal_success"), ".", label="nominal start: success (0/1)")
    ax.axhline(0.95, color="grey", lw=0.8, ls=":")
    ax.set_ylim(-0.05, 1.05)
    ax.set_ylabel("rate")
    ax.legend(fontsize=8, loc="lower right")

    ax = axes[0, 1]
    ax.plot(steps, _series(rows, "nominal_return"), label="nominal start")
    ax.plot(steps, _series(rows, "mean_return"), "--", label="perturbed starts (mean)")
    ret = np.concatenate([_series(rows, "nominal_return"), _series(rows, "mean_return")])
    ret = ret[np.isfinite(ret)]
    if ret.size:
        ax.set_ylim(max(np.min(ret), np.max(ret) - 40.0), np.max(ret) + 0.1 * (np.ptp(ret) + 1e-3))
    ax.set_ylabel("return (the run's final reward weights)")
    ax.legend(fontsize=8)

    ax = axes[1, 0]
    done = _series(rows, "nominal_completed") == 1.0  # time and fuel of completed cycles only
    ax.plot(steps, np.where(done, _series(rows, "T"), np.nan), color="C0", label="cycle time T (s)")
    ax.set_ylabel("T (s)", color="C0")
    T = _series(rows, "T")[done]
    ax.set_ylim(7.5, max(14.0, float(np.nanmax(T)) + 1.0) if T.size and np.isfinite(T).any() else 14.0)
    ax2 = ax.twinx()
    ax2.plot(steps, np.where(done, _series(rows, "fuel_g"), np.nan), color="C1", label="fuel (g)")
    ax2.set_ylabel("fuel (g)", color="C1")
    ax2.set_ylim(40, 130)
    if front is not None:
        ax.axhline(front.T_min, color="C0", ls=":", lw=0.8)
        ax2.axhline(front.fuel_min_g, color="C1", ls=":", lw=0.8)
    ax.set_xlabel("training steps (millions)")
    ax.set_title("nominal cycle, when completed (dotted: minimum time / minimum fuel)", fontsize=9)

    ax = axes[1, 1]
    ax.plot(steps, 100 * _series(rows, "time_gap"), label="time gap")
    ax.plot(steps, 100 * _series(rows, "fuel_gap"), label="fuel gap (same cycle time)")
    late = _series(rows, "lateness_median")
    if np.isfinite(late).any():  # a target-conditioned run (WheelLoaderTarget-v0): targets and lateness
        ax.plot(steps, 100 * _series(rows, "fuel_gap_median"), label="fuel gap, median over the targets")
        ax.plot(steps, 100 * late, label="lateness, median (all evaluation episodes)")
    ax.axhline(100 * GAP_TARGET, color="grey", lw=0.8, ls=":", label="15 % target")
    ax.axhline(0.0, color="k", lw=0.5)
    shown = np.concatenate([_series(rows, k) for k in ("time_gap", "fuel_gap", "fuel_gap_median", "lateness_median")])
    shown = shown[np.isfinite(shown)]
    ax.set_ylim(-10, max(60.0, 100 * float(shown.max()) + 10.0) if shown.size else 60.0)
    ax.set_ylabel("gap to the optimum (%)")
    ax.set_xlabel("training steps (millions)")
    ax.legend(fontsize=8)
    for a in axes.flat:
        a.grid(alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    save_figure(fig, out, dpi=110)
    plt.close(fig)
    return out


def run_braking(path: Path) -> str:
    """The braking of a run's config.json (any version of it: only that field is read); ValueError naming the file."""
    try:
        braking = json.loads(path.read_text())["config"]["braking"]
    except (OSError, ValueError, KeyError, TypeError, RecursionError) as exc:
        raise ValueError(f"{path} is not a readable run config: {type(exc).__name__}: {exc}") from None
    if braking not in ("service", "tc"):
        raise ValueError(f"{path}: its braking must be 'service' or 'tc', got {str(braking)[:40]!r}")
    return braking


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("source", help="a run directory (with eval.csv) or an eval CSV file")
    ap.add_argument("--out", required=True, help="PNG to write")
    ap.add_argument("--braking", default=None, choices=["service", "tc"],
                    help="braking alternative (default: from the run's config.json)")
    ap.add_argument("--title", default=None)
    ap.add_argument("--no-front", action="store_true", help="do not draw the optimum's references")
    ap.add_argument("--front", default=None, metavar="JSON",
                    help="a saved Pareto front (ParetoFront.save) instead of mpc.benchmark.pareto.pareto_front(braking)")
    from agents.train_cli import refuse_repeated_options

    refuse_repeated_options(ap)  # (argparse kept the last of an option given twice, without a word)
    args = ap.parse_args(argv)
    src = Path(args.source)
    csv_path = src / "eval.csv" if src.is_dir() else src
    if not csv_path.is_file():
        ap.error(f"no learning curve at {csv_path} (a run directory with eval.csv, or an eval CSV file)")
    if Path(args.out).suffix.lower() != ".png" or Path(args.out).is_dir():
        ap.error(f"--out must name a .png file, got {args.out!r}")
    if args.front and not Path(args.front).is_file():
        ap.error(f"--front {args.front}: no such file")
    braking = args.braking
    try:  # (a corrupt run file: one line naming it, not a traceback)
        if braking is None and (src / "config.json").exists():
            braking = run_braking(src / "config.json")
        rows = read_eval_csv(csv_path)
    except ValueError as exc:
        ap.error(str(exc))
    braking = braking or "service"
    front = None
    if args.front and not args.no_front:  # (a front given is checked: one of the other braking drew its lines here)
        from mpc.benchmark.pareto import ParetoFront, check_front_of
        from wl_env.params import DEFAULT_PARAMS

        try:
            front = ParetoFront.load(args.front)
            check_front_of(front, braking, DEFAULT_PARAMS)
        except (ValueError, OSError, TypeError, KeyError) as exc:
            ap.error(f"--front {args.front}: {' '.join(str(exc).split())[:300]}")
    elif not args.no_front:
        try:
            from mpc.benchmark.pareto import pareto_front

            front = pareto_front(braking)
        except Exception as e:  # noqa: BLE001  (the figure is drawn without the optimum's lines)
            print(f"warning: no Pareto front ({e})", file=sys.stderr)
    if not rows:
        ap.error(f"{csv_path} holds no evaluation rows: nothing to plot")
    missing = [c for c in ("step", "T", "fuel_g") if c not in rows[0]]  # (another CSV: an empty plot, exit 0)
    if missing:
        ap.error(f"{csv_path} is no evaluation log: it has no {', '.join(missing)} column (eval.csv has {EVAL_FIELDS[0]}, ...)")
    if front is not None:  # score the rows logged while no front was at hand
        from mpc.benchmark.scoring import score_run

        for r in rows:
            if math.isnan(r.get("time_gap", math.nan)) and r.get("nominal_completed") == 1.0:
                s = score_run(r["T"], r["fuel_g"], braking, front=front)
                r["time_gap"], r["fuel_gap"] = s.time_gap, s.fuel_gap
    title = args.title or f"PPO, {braking} braking: deterministic evaluations during training"
    try:
        print(plot(rows, braking, title, Path(args.out), front))
    except OSError as exc:  # an --out folder that cannot be written: one line naming it
        ap.error(f"--out {args.out}: {exc.strerror or exc}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
