"""Train a plan policy (``agents/policies/plan_target_<braking>``) as shipped: PPO on ``WheelLoaderPlan-v1`` over
the ``train`` suite's draws, in stages, each from the stage before's policy with less exploration noise.

    python scripts/train_plan_policy.py --braking tc --seed 0                       # runs/plan_tc_s0_stage{1,2}
    python scripts/train_plan_policy.py --braking tc --seed 0 --export agents/policies/plan_target_tc \\
        --curve docs/learning_curve_plan_target_tc                                  # and ship it
    python scripts/train_plan_policy.py --braking tc --seeds 0 1 2 --ray [ADDRESS]  # 3 seeds as Ray tasks

Stage k is the run ``<log-dir>/plan_<braking>_s<seed>_stage<k>`` of ``scripts/train_ppo.py`` (its config, checkpoints,
``eval.csv``), with the recipe below and the stage's cycles and log-std schedule. Run again, the script keeps the
finished stages and resumes an interrupted one from its newest checkpoint, so a killed job loses at most
``--checkpoint-freq`` cycles. ``--export`` ships the last stage's policy with every stage's run, cycles, wall time
and command in its metadata (``stages``); ``--curve`` writes the learning curve over all stages (CSV and PNG).
``--seeds`` trains several seeds' stages, one seed after another here, or each seed as a Ray task (one CPU) with
``--ray`` (``local``, or a cluster's address; the same folders, on a shared filesystem).

The recipe (docs/benchmarks.md section 7): 2048 loaders, one cycle each per rollout (a plan env step drives every
loader's whole cycle together, and its cost barely grows with the loaders: ``scripts/bench_plan_env.py``), minibatch
512, a (256, 256) network, the fuel weight 8, the lateness charge 50 per unit of relative lateness.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import logging
import shlex
import subprocess
import sys
from dataclasses import dataclass, replace
from pathlib import Path

from agents.policy_files import PolicyFiles, check_policy_output
from agents.train_cli import tyro_options
from wl_env.atomic_io import atomic_path, check_output_file, check_output_folder, write_json_atomic
from wl_env.logs import cli_logging, run_script

log = logging.getLogger("train_plan_policy")

# PPOConfig fields every stage shares (scripts/train_ppo.py's flags of the same names)
RECIPE = {"scenario": "train", "init_noise": 0.0, "n_steps": 1, "batch_size": 512,
          "w_fuel": 8.0, "curriculum_fraction": 0.0, "net_arch": (256, 256), "torch_threads": 1, "progress_bar": False,
          "reward": {"target_distance": 60.0, "target_height": 60.0, "failure": 100.0, "violation": 100.0}}


@dataclass
class Options:
    braking: str = "service"
    env_id: str = "WheelLoaderPlan-v1"  # the plan env (v1 on WheelLoaderTarget-v7 since stop 62; v0 on v6 until then)
    seed: int = 0
    seeds: tuple[int, ...] = ()  # these seeds' stages instead of --seed's (not with --export or --curve)
    ray: str | None = None  # --seeds as Ray tasks on this cluster ("local": a Ray instance on this machine)
    log_dir: str = "runs"
    # per stage (since stop 56; 500 000 + 500 000 until then: 1.15 T_min 11.9 / 10.5 % over 3 seeds against 9.7 / 8.7 %)
    cycles: tuple[int, ...] = (1_000_000, 1_000_000)
    late: float = 50.0  # the lateness charge per unit of relative lateness (the reward's ``late``)
    log_std_init: tuple[float, ...] = (-1.0, -3.0)  # per stage: the Gaussian's log std at the stage's start
    log_std_final: tuple[float, ...] = (-3.5, -4.0)  # per stage: its cap at the stage's end (annealed)
    num_envs: int = 2048  # loaders per rollout (one cycle each)
    eval_freq: int = 200_000  # cycles between evaluations (the learning curve's points)
    eval_episodes: int = 8
    checkpoint_freq: int = 200_000  # cycles
    time_limit: float = 3000.0  # s of wall time per stage (0: none)
    score: bool = True  # score the evaluations against the optimum (--no-score: no Pareto front solved or read)
    export: str | None = None  # ship the last stage's policy as EXPORT.safetensors, ... (agents.ppo.export_policy)
    export_episodes: int = 100  # the shipped metadata's evaluation
    curve: str | None = None  # write the learning curve over the stages to CURVE.csv and CURVE.png


def stage_configs(o: Options) -> list:
    """Each stage's PPOConfig (ConfigError naming a field out of its range)."""
    from wl_env.plan import driven_on

    driven_on(o.env_id, "--env-id")  # (PPOConfig takes any env id: a per-step env under this recipe is not one)
    from agents.ppo_config import ConfigError, PPOConfig
    from agents.train_cli import flag_error

    n = len(o.cycles)
    if n == 0 or len(o.log_std_init) != n or len(o.log_std_final) != n:
        raise ValueError(f"--cycles, --log-std-init and --log-std-final must give one value per stage (1 or more), "
                         f"got {len(o.cycles)}, {len(o.log_std_init)} and {len(o.log_std_final)}")
    if not all(isinstance(c, int) and 1 <= c <= 10**9 for c in o.cycles):  # (was PPOConfig.total_timesteps's error)
        raise ValueError(f"--cycles must be integers in [1, 1000000000], one per stage, got {list(o.cycles)}")
    configs = []
    for k in range(n):
        name = f"plan_{o.braking}_s{o.seed}_stage{k + 1}"
        try:  # (each field an option of the same name: said as the option, not as PPOConfig.num_envs)
            configs.append(PPOConfig(
                **{**RECIPE, "reward": {**RECIPE["reward"], "late": o.late}}, env_id=o.env_id, braking=o.braking, seed=o.seed, log_dir=o.log_dir, run_name=name, total_timesteps=o.cycles[k],
                num_envs=o.num_envs, log_std_init=o.log_std_init[k], log_std_final=o.log_std_final[k],
                eval_freq=o.eval_freq, eval_episodes=o.eval_episodes, checkpoint_freq=o.checkpoint_freq,
                time_limit=o.time_limit, score=o.score, init_policy=str(configs[-1].run_dir) if configs else ""))
        except ConfigError as exc:
            raise flag_error(exc) from None
    return configs


def train_stages(o: Options) -> dict[int, list[dict]]:
    """Train the stages not finished yet of each seed (``--seeds``, else ``--seed``), resuming an interrupted one,
    reading a finished one back, each refused if made with other settings (:func:`agents.seeds.train_one`); the
    stages' summaries per seed."""
    from agents.seeds import on_ray, run_state, train_chain

    command = "python scripts/train_plan_policy.py " + " ".join(map(shlex.quote, sys.argv[1:]))
    chains = {}
    for seed in o.seeds or (o.seed,):
        configs = stage_configs(replace(o, seed=seed))
        for k, cfg in enumerate(configs):
            log.info("seed %d, stage %d: %s (%s)", seed, k + 1, cfg.run_dir,
                     {"done": "finished, kept", "started": "resuming", "new": "training"}[run_state(cfg)])
        chains[seed] = ([c.to_dict() for c in configs], [f"{command}  # stage {k + 1}" for k in range(len(configs))])
    if o.ray is not None:
        done = on_ray({f"seed {seed}": (train_chain, chain) for seed, chain in chains.items()}, o.ray)
        return {seed: done[f"seed {seed}"] for seed in chains}
    return {seed: train_chain(*chain) for seed, chain in chains.items()}


def write_curve(o: Options, summaries: list[dict], path: Path) -> None:
    """The learning curve over the stages: each stage's ``eval.csv`` rows, its steps and wall time counted on from
    the stages before (a stage's first row, its start policy, is the stage before's last)."""
    from agents.ppo import read_eval_csv

    rows: list[dict] = []
    steps = wall = 0.0
    for k, (cfg, summary) in enumerate(zip(stage_configs(o), summaries, strict=True)):
        for i, row in enumerate(read_eval_csv(cfg.run_dir / "eval.csv")):
            if k > 0 and i == 0:
                continue
            rows.append({**row, "step": row["step"] + steps, "wall_time": row["wall_time"] + wall})
        steps += summary["num_timesteps"]
        wall += summary["wall_time"]
    if not rows:
        raise ValueError(f"no evaluation rows in the stages' eval.csv under {o.log_dir} (--eval-freq {o.eval_freq})")
    csv_path, png_path = path.with_name(path.name + ".csv"), path.with_name(path.name + ".png")
    with atomic_path(csv_path) as tmp, open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    title = f"plan policy ({o.braking}): PPO on {o.env_id}, {len(summaries)} stages, seed {o.seed}"
    done = subprocess.run([sys.executable, str(Path(__file__).with_name("plot_learning_curve.py")), str(csv_path),
                           "--braking", o.braking, "--out", str(png_path), "--title", title,
                           *([] if o.score else ["--no-front"])], capture_output=True)
    if done.returncode:  # (was a CalledProcessError's traceback after hours of training, naming neither run nor csv)
        said = [line for line in done.stderr.decode("utf-8", "replace").splitlines() if line.strip()]
        why = " ".join(said[-1].split())[:300] if said else "no message"
        raise ValueError(f"--curve {o.curve}: plotting the learning curve failed (plot_learning_curve.py exit "
                         f"{done.returncode}: {why}); the trained stages are kept in "
                         f"{', '.join(str(cfg.run_dir) for cfg in stage_configs(o))}, the curve's rows in {csv_path} "
                         f"(run the same command again to read them back and draw it)")


def export(o: Options, summaries: list[dict]) -> dict:
    """Ship the last stage's policy with every stage in its metadata."""
    from agents.ppo import export_policy
    from wl_env.plan import driven_on

    configs = stage_configs(o)
    stages = [{"run": str(cfg.run_dir), "num_timesteps": int(s["num_timesteps"]), "wall_time_s": round(float(s["wall_time"]), 1),
               "log_std": [cfg.log_std_init, cfg.log_std_final], "commands": list(s.get("commands", []))}
              for cfg, s in zip(configs, summaries, strict=True)]
    path = Path(o.export)
    method = (f"PPO on {o.env_id} (one plan of 14 numbers per cycle, driven on {driven_on(o.env_id)}) over the "
              f"train suite's draws, targets T_min..2.5 T_min, in {len(stages)} stages "
              f"({' + '.join(f'{c:,}' for c in o.cycles)} cycles), each from the stage before's policy with less "
              f"exploration noise; seed {o.seed} (scripts/train_plan_policy.py)")
    return export_policy(configs[-1].run_dir, path.parent, path.name, n_episodes=o.export_episodes, score=False, extra={
        "num_timesteps": sum(s["num_timesteps"] for s in stages),
        "training_wall_time_s": round(sum(s["wall_time_s"] for s in stages), 1),
        "stages": stages, "method": method})


def stages_file(o: Options, seed: int) -> Path:
    """Where a seed's stages are recorded: ``<log-dir>/plan_<braking>_s<seed>_stages.json``."""
    return Path(o.log_dir) / f"plan_{o.braking}_s{seed}_stages.json"


def main(o: Options) -> dict[int, dict]:
    """Each seed's stages trained (and the one seed's policy shipped, its curve written, if asked); per seed the
    stages' steps and wall time, also written to ``<log-dir>/plan_<braking>_s<seed>_stages.json``."""
    stage_configs(o)  # (every option checked before any work)
    if o.seeds and (o.export is not None or o.curve is not None):
        raise ValueError("--export and --curve ship one seed's policy: give it by --seed, not --seeds")
    if len(set(o.seeds)) != len(o.seeds) or not all(0 <= seed < 2**31 for seed in o.seeds):
        raise ValueError(f"--seeds must be distinct integers in [0, 2**31 - 1], got {o.seeds}")
    if o.ray is not None:
        from mpc.workers import check_ray_address

        check_ray_address(o.ray)
    if not 1 <= o.export_episodes <= 10_000:
        raise ValueError(f"--export-episodes must be an integer in [1, 10000], got {o.export_episodes}")
    for name in ("export", "curve"):
        if getattr(o, name) is not None and not getattr(o, name).strip():
            raise ValueError(f"--{name} must name a path, got an empty string")
    check_output_folder(o.log_dir, f"--log-dir {o.log_dir}")
    # each file they write, not only their folder: a folder at CURVE.csv or EXPORT.json failed after the training
    if o.export is not None:
        check_policy_output(o.export, "--export")
    if o.curve is not None:
        for suffix in (".csv", ".png"):
            check_output_file(Path(o.curve).with_name(Path(o.curve).name + suffix), f"--curve {o.curve}")
    for seed in o.seeds or (o.seed,):  # (each seed's record of its stages: a folder there failed after the training)
        check_output_file(stages_file(o, seed), "--log-dir's stages record")
    # (no two of them one file: --export runs/plan_service_s0_stages wrote the stages record over the shipped policy's
    # metadata; --curve <stage run>/eval wrote the curve over the eval.csv it is drawn from)
    from wl_env.atomic_io import refuse_one_path_twice

    written = [("--log-dir's stages record", stages_file(o, seed)) for seed in o.seeds or (o.seed,)]
    if o.export is not None:
        written += [("--export", path) for path in dataclasses.astuple(PolicyFiles.of(o.export))]
    if o.curve is not None:
        written += [("a stage's eval.csv (the curve's rows)", cfg.run_dir / "eval.csv") for cfg in stage_configs(o)]
        written += [("--curve", f"{o.curve}{suffix}") for suffix in (".csv", ".png")]
    refuse_one_path_twice(written)
    results = {}
    for seed, summaries in train_stages(o).items():
        out = {"stages": [{"num_timesteps": s["num_timesteps"], "wall_time_s": s["wall_time"]} for s in summaries],
               "wall_time_s": sum(s["wall_time"] for s in summaries)}
        if o.curve:
            write_curve(o, summaries, Path(o.curve))
        if o.export:
            out["export"] = export(o, summaries)["files"]
        write_json_atomic(stages_file(o, seed), out)
        results[seed] = out
    print(json.dumps(results, indent=2, default=str))
    return results


if __name__ == "__main__":
    with cli_logging(names=("agents",)):  # (the stages' evaluation lines, as scripts/train_ppo.py shows them)
        run_script("train_plan_policy", lambda: main(tyro_options(Options)))
