"""The imitation baseline: behaviour cloning of the MPC on ``train`` scenarios, at target cycle times.

    python scripts/train_bc.py --braking tc --episodes 40 --workers 2 --export agents/policies/bc_tc

1. MPC demonstrations in ``--env-id`` (``agents.imitation.collect_demos``; WheelLoaderTarget-v1: action 0 the
   engine-speed request to the governor, the MPC's injection translated; for the assisted drivers of v2 and
   v3, v1 episodes labelled as the driver's actions, ``agents.imitation.driver_labels``): fresh draws of the
   ``train`` distribution, targets uniform in ``--target`` times the scenario's estimated T_min, a
   ``--fast-share`` of them as fast as possible. One file per episode in ``--demos`` (default
   ``<log-dir>/demos_<demonstrations env>_<braking>_s<demo-seed>``): a killed run resumes with the episodes it has.
2. The PPO policy network (``--net-arch``) regressed onto the expert's actions (``agents.imitation.clone``),
   written as the run ``<log-dir>/<run-name>/final`` (the layout of a PPO run: ``wl evaluate --model``
   takes it; ``wl train --init-policy <run>/final/policy`` fine-tunes it with PPO).
3. ``--dagger-rounds N``: DAgger. Each round the clone drives ``--dagger-episodes`` new draws (the
   expert's own action applied with probability ``--beta`` per step), the MPC labels every state it
   visits, and the clone is fitted again on all demonstrations so far. A WheelLoaderTarget-v3 clone
   drives v3, and the MPC's plan from each state labels its fractions (``agents.imitation.plan_labels``).
4. ``--graft-base POLICY`` (WheelLoaderTarget-v3): no clone; the trained v2 policy POLICY is kept and only
   v3's fourth action, the coasting fraction, is fitted to the expert's shifts
   (``agents.imitation.graft_early_shift``), a start for PPO fine-tuning (``--init-policy``).
   ``--clone-base POLICY``: the clone starts from the trained policy POLICY of its env (its network and
   observation statistics) and keeps its critic, a start for PPO fine-tuning with a trained critic.
5. ``--export PATH``: shipped pickle-free with a fresh evaluation at three targets (agents.ppo.export_policy).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import shlex
import sys
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agents.train_cli import tyro_options  # noqa: E402
from mpc import interrupt  # noqa: E402
from wl_env.logs import PACKAGES, run_script  # noqa: E402

log = logging.getLogger("train_bc")


@dataclass
class Options:
    braking: str = "service"  # 'service' or 'tc'
    episodes: int = 40  # MPC demonstration episodes
    demo_seed: int = 0  # seed of the demonstrations' scenario and target draws
    target: tuple[float, float] = (1.05, 2.5)  # target ratios to T_min the demonstrations are drawn from
    fast_share: float = 0.2  # share of demonstrations as fast as possible (the MPC's minimum-time mode)
    workers: int = 1  # processes collecting demonstrations
    demos: str = ""  # demonstration folder (default <log-dir>/demos_<demonstrations env>_<braking>_s<demo-seed>)
    seed: int = 0  # seed of the network's initialization and the training/validation split
    epochs: int = 300  # passes over the demonstrations
    learning_rate: float = 1e-3  # Adam step size
    batch_size: int = 1024
    net_arch: tuple[int, ...] = (64, 64)  # hidden layers (the PPO runs' default, so PPO can fine-tune it)
    log_dir: str = "runs"
    run_name: str = ""  # default bc_<braking>_s<seed>
    export: str = ""  # ship as PATH.safetensors, PATH_vecnormalize.npz, PATH.json
    export_episodes: int = 16  # validation draws per target of the export's evaluation
    dagger_rounds: int = 0  # DAgger rounds after the first clone (0: behaviour cloning only)
    dagger_episodes: int = 20  # episodes the clone drives per round
    beta: float = 0.2  # DAgger: the chance per step that the expert's action is applied instead of the clone's
    graft_base: str = ""  # a trained WheelLoaderTarget-v2 policy: keep it and fit only v3's coasting fraction onto it
    clone_base: str = ""  # a trained policy of the clone's env: the clone starts from its network and observation
    # statistics, and keeps its critic (for PPO fine-tuning from the clone: --init-policy <run>/final/policy)
    env_id: str = "WheelLoaderTarget-v1"  # the clone's env (v0: action 0 the injection; v2/v3: the assisted driver,
    # labelled from v1 demonstrations)

    def __post_init__(self) -> None:
        """The numbers checked by name before anything runs (a bad one used to surface after the demonstrations,
        ~20 s each, or not at all: --epochs 0 shipped an untrained clone)."""
        rules = {"episodes": (1, 10_000), "epochs": (1, 100_000), "batch_size": (1, 2**20), "workers": (1, 256),
                 "export_episodes": (1, 10_000), "dagger_rounds": (0, 100), "dagger_episodes": (1, 10_000),
                 "demo_seed": (0, 2**20)}  # (a seed out of range was refused as "seed", another flag)
        for name, (lo, hi) in rules.items():
            v = getattr(self, name)
            if not (isinstance(v, int) and not isinstance(v, bool) and lo <= v <= hi):
                raise ValueError(f"--{name.replace('_', '-')} must be an integer in [{lo}, {hi}], got {v!r}")
        for name, allowed, ok in (("learning_rate", "(0, 1]", lambda v: 0 < v <= 1), ("beta", "[0, 1]", lambda v: 0 <= v <= 1),
                                  ("fast_share", "[0, 1]", lambda v: 0 <= v <= 1)):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and ok(v)):
                raise ValueError(f"--{name.replace('_', '-')} must be a number in {allowed}, got {v!r}")


def write_policy_copy(stem: str | Path, out: Path) -> None:
    """The pickle-free policy ``stem`` written again as ``out`` (read and checked, then its three files)."""
    from agents.policy_files import read_policy, write_policy

    network, normalization, meta = read_policy(stem)
    write_policy(network, normalization, out, meta)


def main(o: Options, command: str) -> int:
    from agents.imitation import DEMO_ENV_ID, DRIVER_ENV_IDS, METHOD, DemoSettings, clone, collect_demos
    from agents.ppo import export_policy
    from agents.ppo_config import ConfigError, PPOConfig
    from agents.train_cli import flag_error

    try:  # (each field an option of the same name: said as the option, not as PPOConfig.net_arch)
        cfg = PPOConfig(braking=o.braking, env_id=o.env_id, scenario="train", init_noise=0.0, seed=o.seed,
                        net_arch=o.net_arch, log_dir=o.log_dir, run_name=o.run_name or f"bc_{o.braking}_s{o.seed}",
                        progress_bar=False)
    except ConfigError as exc:
        raise flag_error(exc) from None
    if o.env_id == DRIVER_ENV_IDS[0] and o.dagger_rounds:
        raise ValueError(f"dagger_rounds must be 0 with env_id {o.env_id}: its braking labels come from the expert's "
                         f"own cycle (where it shifted); {DRIVER_ENV_IDS[1]}'s come from the MPC's plans")
    if o.graft_base and o.clone_base:
        raise ValueError("give graft_base or clone_base, not both")
    if o.graft_base and (o.env_id != DRIVER_ENV_IDS[1] or o.dagger_rounds or o.export):
        raise ValueError(f"graft_base needs env_id {DRIVER_ENV_IDS[1]}, no dagger_rounds and no export "
                         f"(fine-tune the graft with PPO: --init-policy <run>/final/policy)")
    # the output paths checked now, not after the demonstrations and the fit (an --export into a file's folder failed last)
    from wl_env.atomic_io import check_output_folder

    check_output_folder(o.log_dir, f"--log-dir {o.log_dir}")
    if o.demos:
        check_output_folder(o.demos, f"--demos {o.demos}")
    if o.export:  # (each of its files: a folder at PATH.json failed after the demonstrations and the fit)
        from agents.policy_files import check_policy_output

        check_policy_output(o.export, "--export")
        if o.clone_base:  # (--clone-base P --export P wrote the clone over the policy it started from, after the work)
            from agents.evaluate import policy_input_files
            from agents.policy_files import PolicyFiles
            from wl_env.atomic_io import check_not_an_input

            for path in dataclasses.astuple(PolicyFiles.of(o.export)):  # (the files write_policy writes)
                check_not_an_input(path, policy_input_files(o.clone_base), "--export")
    from agents.imitation import check_run_folder

    check_run_folder(cfg)  # (a PPO run of the same name: its policy was replaced after the demonstrations)
    if o.clone_base or o.graft_base:  # (read and checked now, not after an hour of demonstrations)
        from agents.imitation import read_base

        if o.clone_base:
            read_base(o.clone_base, cfg, o.env_id)
        else:
            read_base(o.graft_base, cfg, DRIVER_ENV_IDS[0])
    demo_env = DEMO_ENV_ID[o.env_id]  # (an assisted driver is cloned from the expert's own v1 cycles)
    settings = DemoSettings(o.braking, o.demo_seed, tuple(o.target), o.fast_share, env_id=demo_env)
    folder = o.demos or str(Path(o.log_dir) / f"demos_{demo_env}_{o.braking}_s{o.demo_seed}")
    try:
        demos = collect_demos(settings, o.episodes, folder, workers=o.workers)
    except KeyboardInterrupt:
        log.info("interrupted; the episodes in %s are kept, the same command goes on from them", folder)
        return interrupt.exit_code()
    meta = {"commands": [command], "demos": {
        "folder": folder, "episodes": o.episodes, "seed": o.demo_seed, "target": list(o.target),
        "fast_share": o.fast_share, "dagger_rounds": o.dagger_rounds, "dagger_episodes": o.dagger_episodes,
        "beta": o.beta}}
    if o.graft_base:
        from agents.imitation import graft_early_shift

        graft = graft_early_shift(o.graft_base, demos, cfg, extra=meta)
        log.info("grafted the coasting fraction onto %s from %d episodes: squared error %.4f (a constant's %.4f) -> %s",
                 o.graft_base, graft.episodes, graft.loss, graft.constant_loss, graft.policy)
        return 0
    fit = {"epochs": o.epochs, "learning_rate": o.learning_rate, "batch_size": o.batch_size, "extra": meta,
           "base": o.clone_base or None}
    result = clone(demos, cfg, **fit)
    log.info("cloned %d episodes (%d dropped), %d samples: validation loss %.5f -> %s", result.episodes,
             result.episodes_dropped, result.samples, result.validation_loss, result.policy)
    for r in range(1, o.dagger_rounds + 1):
        # each round's learner is a copy of the clone it starts from (the clone is refitted into final/)
        learner = Path(o.log_dir) / f"{cfg.name}_dagger{r}_learner"
        write_policy_copy(result.policy, learner)
        # (a v3 driver's rounds run in v3: the MPC labels them from its plans, agents.imitation.plan_labels)
        round_settings = dataclasses.replace(settings, seed=o.demo_seed + 1000 * r, learner=str(learner), beta=o.beta,
                                             env_id=o.env_id if o.env_id in DRIVER_ENV_IDS else settings.env_id)
        try:
            # (a v3 round's episodes are its own labels: a folder apart from a v1 round's, which keeps its name)
            suffix = f"_{round_settings.env_id}" if round_settings.env_id != settings.env_id else ""
            demos += collect_demos(round_settings, o.dagger_episodes, f"{folder}_dagger{r}{suffix}", workers=o.workers)
        except KeyboardInterrupt:
            log.info("interrupted; the same command goes on from the episodes on disk")
            return interrupt.exit_code()
        result = clone(demos, cfg, **fit)
        log.info("DAgger round %d: %d episodes, %d samples: validation loss %.5f", r, result.episodes, result.samples,
                 result.validation_loss)
    if o.export:
        out = Path(o.export)
        shipped = export_policy(cfg.run_dir, out.parent, out.name, n_episodes=o.export_episodes,
                                extra={"method": METHOD, "clone": result.__dict__, "demos": meta["demos"]})
        print(json.dumps(shipped["evaluation"], indent=2, default=str))
    return 0


if __name__ == "__main__":
    argv = sys.argv[1:]
    # (run_script: bad options one line, Ctrl-C or SIGTERM anywhere exit 130 / 143; it was a traceback outside the
    # demonstrations' collection)
    run_script("train_bc", lambda: sys.exit(main(tyro_options(Options, args=argv),
                                                  "python scripts/train_bc.py " + shlex.join(argv))),
               loggers=(*PACKAGES, "train_bc"))
