"""The MPC's model-error estimator on the mismatch corners of ``bench_mpc.py`` (the synchronous default, minimum time,
the nominal model; the plant's payload x0.8 / 1.2 and rolling resistance x0.7 / 1.3): per cycle the estimates it
ends on against the plant's (lift gain = plant payload / model payload, acceleration gain = model mass / plant mass,
offset = the rolling-resistance error in m/s^2), the plans' one-step engine-speed error (the moving RMS,
``ModelErrorEstimator.omega_error_rms``), and the cycle: time, fuel, reversing-point error, violation, eased controls.
Usage::

    python scripts/bench_estimator.py [--braking service tc] [--json PATH]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench_mpc import MISMATCH  # noqa: E402  (its mismatch corners: (payload, rolling resistance) scales)

from agents.train_cli import refuse_repeated_values  # noqa: E402
from mpc.controller.mpc import MPCConfig, MPCController, run_closed_loop  # noqa: E402
from wl_env.atomic_io import check_output_option, write_json_atomic  # noqa: E402
from wl_env.logs import run_script  # noqa: E402
from wl_env.params import DEFAULT_PARAMS  # noqa: E402


def run(braking: str, payload: float, rolling: float) -> dict:
    plant = DEFAULT_PARAMS.variant(payload_scale=payload, rolling_scale=rolling)
    ctrl = MPCController(braking)  # the nominal model
    ep = run_closed_loop(braking, MPCConfig(mode="time"), plant_params=plant, score=False, controller=ctrl).episode
    est = ctrl.estimator
    return {"braking": braking, "payload_scale": payload, "rolling_scale": rolling, "T": ep.T, "fuel_g": ep.fuel_g,
            "success": ep.success, "reversing_error_m": ep.reversing_error_m, "max_violation": ep.max_violation,
            "eased": int(ctrl.safety_eased), "lift_gain": float(est.lift_gain), "plant_lift_gain": payload,
            "accel_gain": float(est.theta[0]), "plant_accel_gain": DEFAULT_PARAMS.M_tot / plant.M_tot,
            "accel_offset": float(est.theta[1]),
            "plant_accel_offset": (DEFAULT_PARAMS.F_roll - plant.F_roll) / plant.M_tot,
            "omega_error_rms": float(est.omega_error_rms)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--braking", choices=("service", "tc"), nargs="+", default=["service", "tc"])
    ap.add_argument("--json", metavar="PATH")
    from agents.train_cli import refuse_repeated_options

    refuse_repeated_options(ap)  # (argparse kept the last of an option given twice, without a word)
    args = ap.parse_args()
    check_output_option(ap, args.json, "--json")
    try:  # (each corner run twice)
        refuse_repeated_values("--braking", args.braking, "a braking alternative")
    except ValueError as exc:
        ap.error(str(exc))
    rows = []
    for braking in args.braking:
        for payload, rolling in MISMATCH:
            r = run(braking, payload, rolling)
            rows.append(r)
            print(f"{braking} payload x{payload} rolling x{rolling}: T {r['T']:.1f} s, fuel {r['fuel_g']:.2f} g, on the "
                  f"marks {r['success']}, reversing error {100 * (r['reversing_error_m'] or 0.0):+.1f} cm, violation "
                  f"{100 * r['max_violation']:.2f} %; lift gain {r['lift_gain']:.4f} (plant {payload:g}), acceleration "
                  f"gain {r['accel_gain']:.4f} ({r['plant_accel_gain']:.4f}), offset {r['accel_offset']:+.4f} "
                  f"({r['plant_accel_offset']:+.4f}) m/s^2; one-step engine error RMS {r['omega_error_rms']:.4f} rad/s",
                  flush=True)
    if args.json:
        write_json_atomic(args.json, {"command": " ".join(sys.argv), "rows": rows})


if __name__ == "__main__":
    run_script("bench_estimator", main)  # (Ctrl-C: exit 130; the JSON is written only at the end, nothing partial is left)
