"""The options of a PPO training run (:class:`PPOConfig`), apart from :mod:`agents.ppo` so that the command
line (``wl train --help``, ``scripts/train_ppo.py``) is built without importing torch and stable-baselines3."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from wl_env import cycle
from wl_env.env import TARGET_POWER_RANGE
from wl_env.params import MAX_NUM_ENVS, is_real_number, plain

# the registered ids (wl_env/__init__.py) and suites (wl_env/suites), named here so that the command line is
# built without importing gymnasium
ENV_IDS = ("WheelLoader-v1", "WheelLoader-v2", "WheelLoaderTarget-v0", "WheelLoaderTarget-v1", "WheelLoaderTarget-v2",
           "WheelLoaderTarget-v3", "WheelLoaderTarget-v4", "WheelLoaderTarget-v5", "WheelLoaderTarget-v6",
           "WheelLoaderTarget-v7", "WheelLoaderPlan-v0", "WheelLoaderPlan-v1")
TARGET_ENV_ID = "WheelLoaderTarget-v0"  # the target task with the injection as action 0 (the MPC's demonstrations)
# v1: action 0 is the engine-speed governor's request; v2: v1 through the stopping assist (3 actions); v3: v2
# whose driver may end a leg early and coast (4 actions); v4: v3 with the assist's guards (wl_env.assist); v5: v4
# with the lift's engine floor; v6: v5 whose TC lift-off loads the engine with a full lift; v7: v6 braking on the step grid
TARGET_ENV_IDS = ("WheelLoaderTarget-v0", "WheelLoaderTarget-v1", "WheelLoaderTarget-v2", "WheelLoaderTarget-v3",
                  "WheelLoaderTarget-v4", "WheelLoaderTarget-v5", "WheelLoaderTarget-v6", "WheelLoaderTarget-v7")
COAST_ENV_IDS = TARGET_ENV_IDS[3:]  # the drivers with the coasting fraction (4 actions)
PLAN_ENV_IDS = ("WheelLoaderPlan-v0", "WheelLoaderPlan-v1")  # the target task with one decision per cycle (wl_env.plan): 14 actions
TARGETED_ENV_IDS = TARGET_ENV_IDS + PLAN_ENV_IDS  # the envs with a target cycle time per episode
SUITE_NAMES = ("nominal", "train", "test", "corners")
MAX_TORCH_THREADS = 1024  # torch.set_num_threads(100000) segfaults (measured); machines have far fewer cores
MAX_LAYER_WIDTH = 4096  # units per hidden layer: far above what a 12-input policy needs, a guard against typos
# steps per rollout (n_steps * num_envs): SB3's buffer holds ~90 bytes a step (1.5 GB at this cap, the shipped
# recipe's 8192 far below); more failed with a traceback allocating it (numpy's MemoryError)
MAX_ROLLOUT = 2**24
# perturbed starts per evaluation (eval_episodes, `wl train --export-episodes`): one evaluation runs them and the
# nominal start, at most agents.evaluate.MAX_EPISODES episodes; a target env's drew 10**9 scenarios (a hang) after
# the training, a v1 evaluation failed there by the evaluation's name
MAX_EVAL_EPISODES = 99_999
# bytes of a run folder's JSON files (config.json, summary.json, checkpoints/latest.json) read back: a few kB each; read
# as regular files of at most this (wl_env.atomic_io.read_regular_file: a FIFO in their place hung a resume for good)
MAX_RUN_JSON_BYTES = 2**24


class ConfigError(ValueError):
    """A PPOConfig field out of its range; ``field`` names it (the command line turns it into ``--field``)."""

    def __init__(self, name: str, requirement: str, value: Any) -> None:
        super().__init__(f"PPOConfig.{name} must be {requirement}, got {value!r}")
        self.field, self.requirement, self.value = name, requirement, value


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


MAX_SEED = 2**31 - 1  # the largest seed of a training run or an evaluation (gymnasium's env seeds add steps to it)

# field -> (requirement as said in the error, test); a value is a number only if finite and not a bool
_RULES: dict[str, tuple[str, Any]] = {
    "env_id": (f"one of {', '.join(ENV_IDS)}", lambda v: v in ENV_IDS),
    "scenario": (f"'' (the paper's cycle) or a suite name ({', '.join(SUITE_NAMES)})", lambda v: v in ("", *SUITE_NAMES)),
    "target": ("a range (lo, hi) of target ratios to T_min within [1, 3]",
               lambda v: len(v) == 2 and all(is_real_number(x) and 1 <= x <= 3 for x in v) and v[0] <= v[1]),
    "target_power": ("a number in [{:g}, {:g}] (the target ratio's draw: lo + (hi - lo) u**power; 1 uniform)".format(
        *TARGET_POWER_RANGE), lambda v: is_real_number(v) and TARGET_POWER_RANGE[0] <= v <= TARGET_POWER_RANGE[1]),
    "init_policy": ("'' or the path of a pickle-free policy", lambda v: isinstance(v, str) and len(v) <= 4096),
    "seed": ("an integer in [0, 2**31 - 1]", lambda v: _is_int(v) and 0 <= v <= MAX_SEED),  # (env seeds add the step)
    "total_timesteps": ("an integer >= 1", lambda v: _is_int(v) and v >= 1),
    "num_envs": (f"an integer in [1, {MAX_NUM_ENVS}]", lambda v: _is_int(v) and 1 <= v <= MAX_NUM_ENVS),
    "log_dir": ("a non-empty folder name", lambda v: isinstance(v, str) and v.strip() != "" and len(v) <= 4096),
    "run_name": ("a name of at most 200 characters without path separators", lambda v: isinstance(v, str)
                 and "/" not in v and "\\" not in v and v not in (".", "..") and len(v) <= 200),
    "time_limit": ("a finite number of seconds >= 0 (0: off)", lambda v: is_real_number(v) and v >= 0),
    "torch_threads": (f"an integer in [1, {MAX_TORCH_THREADS}]", lambda v: _is_int(v) and 1 <= v <= MAX_TORCH_THREADS),
    "progress_bar": ("true or false", lambda v: isinstance(v, bool)),
    "w_fuel": ("a finite number >= 0", lambda v: is_real_number(v) and v >= 0),
    "w_time": ("a finite number >= 0", lambda v: is_real_number(v) and v >= 0),
    "reward": ("a mapping of RewardConfig fields to finite numbers",
               lambda v: isinstance(v, dict) and all(map(is_real_number, v.values()))),
    "init_noise": ("a number in [0, 1]", lambda v: is_real_number(v) and 0 <= v <= 1),
    "max_time": ("a number of seconds in [0.5, 3600] (5 control steps to an hour)",
                 lambda v: is_real_number(v) and 0.5 <= v <= 3600),
    "curriculum_start": ("a mapping of RewardConfig fields to finite numbers",
                         lambda v: isinstance(v, dict) and all(map(is_real_number, v.values()))),
    "curriculum_fraction": ("a number in [0, 1]", lambda v: is_real_number(v) and 0 <= v <= 1),
    "learning_rate": ("a number in (0, 1]", lambda v: is_real_number(v) and 0 < v <= 1),
    "lr_schedule": ("'constant' or 'linear'", lambda v: v in ("constant", "linear")),
    "n_steps": ("an integer >= 1", lambda v: _is_int(v) and v >= 1),
    "batch_size": ("an integer >= 2", lambda v: _is_int(v) and v >= 2),  # (SB3 asserts it: advantages normalized)
    "n_epochs": ("an integer >= 1", lambda v: _is_int(v) and v >= 1),
    "gamma": ("a number in (0, 1]", lambda v: is_real_number(v) and 0 < v <= 1),
    "gae_lambda": ("a number in [0, 1]", lambda v: is_real_number(v) and 0 <= v <= 1),
    "clip_range": ("a number in (0, 10]", lambda v: is_real_number(v) and 0 < v <= 10),
    "ent_coef": ("a number in [0, 100]", lambda v: is_real_number(v) and 0 <= v <= 100),
    "vf_coef": ("a number in [0, 100]", lambda v: is_real_number(v) and 0 <= v <= 100),
    "max_grad_norm": ("a number in (0, 1e6]", lambda v: is_real_number(v) and 0 < v <= 1e6),
    "target_kl": ("none or a finite number > 0", lambda v: v is None or (is_real_number(v) and v > 0)),
    "net_arch": (f"one or more layer widths, integers in [1, {MAX_LAYER_WIDTH}]",
                 lambda v: len(v) >= 1 and all(_is_int(n) and 1 <= n <= MAX_LAYER_WIDTH for n in v)),
    # (1e308 passed as finite and failed in torch after the env's build, naming no flag)
    "log_std_init": ("a number in [-20, 5]", lambda v: is_real_number(v) and -20 <= v <= 5),
    "log_std_final": ("none or a number in [-20, 5]", lambda v: v is None or (is_real_number(v) and -20 <= v <= 5)),
    "shift_bias_init": ("a number in [-100, 100]", lambda v: is_real_number(v) and -100 <= v <= 100),
    "coast_bias_init": ("a number in [-100, 100]", lambda v: is_real_number(v) and -100 <= v <= 100),
    "fuel_bias_init": ("a number in [-100, 100]", lambda v: is_real_number(v) and -100 <= v <= 100),
    "bucket_bias_init": ("a number in [-100, 100]", lambda v: is_real_number(v) and -100 <= v <= 100),
    "bounded_mean": ("true or false", lambda v: isinstance(v, bool)),
    "use_sde": ("true or false", lambda v: isinstance(v, bool)),
    "sde_sample_freq": ("an integer >= -1 (-1: once per rollout)", lambda v: _is_int(v) and v >= -1),
    "norm_obs": ("true or false", lambda v: isinstance(v, bool)),
    "norm_reward": ("true or false", lambda v: isinstance(v, bool)),
    "eval_freq": ("an integer >= 1", lambda v: _is_int(v) and v >= 1),
    "eval_episodes": (f"an integer >= 0, at most {MAX_EVAL_EPISODES}",
                      lambda v: _is_int(v) and 0 <= v <= MAX_EVAL_EPISODES),
    "eval_init_noise": ("a number in [0, 1]", lambda v: is_real_number(v) and 0 <= v <= 1),
    "score": ("true or false", lambda v: isinstance(v, bool)),
    "checkpoint_freq": ("an integer >= 1", lambda v: _is_int(v) and v >= 1),
    "keep_checkpoints": ("an integer >= 1", lambda v: _is_int(v) and v >= 1),
    "bc_demos": ("'' or a folder of demonstration episodes", lambda v: isinstance(v, str)),
    "bc_weight": ("a finite number >= 0", lambda v: is_real_number(v) and v >= 0),
    "bc_fraction": ("a number in (0, 1]", lambda v: is_real_number(v) and 0 < v <= 1),
}


@dataclass
class PPOConfig:
    """One PPO training run. The defaults are the recipe of the shipped policies (their exact settings
    and commands are in ``agents/policies/ppo_<braking>.json``)."""

    # --- run
    braking: str = field(default="service", metadata={"help": "braking alternative: 'service' or 'tc'"})
    env_id: str = field(default="WheelLoader-v1", metadata={
        "help": "environment: WheelLoader-v1 (the paper's cycle, the shipped nominal policies), WheelLoader-v2 "
                "(scenarios observed), WheelLoaderTarget-v0 (v2 with a target cycle time per episode) or "
                "WheelLoaderTarget-v1 (v0 with an engine-speed request as action 0, through the engine's governor) or "
                "WheelLoaderTarget-v2 (v1 through the stopping assist: request, bucket, braking fraction) or "
                "WheelLoaderTarget-v3 (v2 with a 4th action: the coasting fraction, where a leg ends early to coast) or "
                "WheelLoaderTarget-v4 (v3 with the assist's guards: creep floor, last lift, TC lift timing) or "
                "WheelLoaderTarget-v5 (v4 with the lift's engine floor: the request held up while the bucket lifts) or "
                "WheelLoaderTarget-v6 (v5 whose TC lift-off loads the engine with a full lift) or "
                "WheelLoaderTarget-v7 (v6 whose assist brakes on the step grid: the first braking step takes up the rest) or "
                "WheelLoaderPlan-v0 (one decision per cycle: a phase-parametric plan driven on v6; each step a cycle) or "
                "WheelLoaderPlan-v1 (the same plan driven on v7)"})
    scenario: str = field(default="", metadata={
        "help": "scenario suite the episodes are drawn from, e.g. 'train' (v2 and the target env; '': the paper's cycle)"})
    target: tuple[float, float] = field(default=(1.0, 2.5), metadata={
        "help": "WheelLoaderTarget-v0/v1: range of the target cycle time, as ratios to the scenario's T_min"})
    target_power: float = field(default=1.0, metadata={
        "help": "the target ratio's draw in that range: lo + (hi - lo) u**power, u uniform; 1 uniform, "
                "above 1 more fast targets"})
    seed: int = field(default=0, metadata={"help": "seed of PPO, torch and the environments"})
    total_timesteps: int = field(default=12_000_000, metadata={"help": "environment steps to train for"})
    num_envs: int = field(default=64, metadata={"help": "loaders stepped together (native vector env)"})
    log_dir: str = field(default="runs", metadata={"help": "parent folder of run directories"})
    run_name: str = field(default="", metadata={"help": "run directory name (default ppo_<braking>_s<seed>)"})
    time_limit: float = field(
        default=0.0, metadata={"help": "stop after this much training wall time (s, summed over resumes; 0: off)"})
    torch_threads: int = field(default=1, metadata={"help": "torch.set_num_threads (1 is fastest for small MLPs)"})
    progress_bar: bool = field(default=True, metadata={"help": "show a tqdm/rich progress bar"})
    init_policy: str = field(default="", metadata={
        "help": "start from this pickle-free policy's weights and normalization (e.g. a behaviour-cloned one, "
                "scripts/train_bc.py; the same network; '': a fresh network)"})
    # --- environment and reward (RewardConfig fields by name; see wl_env.episode.RewardConfig)
    w_fuel: float = field(default=2.0, metadata={"help": "fuel weight of the reward (RewardConfig.w_fuel)"})
    w_time: float = field(default=3.0, metadata={
        "help": "time weight of the reward (RewardConfig.w_time; WheelLoaderTarget-v0: unused, its lateness term replaces it)"})
    reward: dict[str, float] = field(
        default_factory=lambda: {"target_distance": 60.0, "target_height": 60.0, "failure": 100.0},
        metadata={"help": "other RewardConfig fields, e.g. --reward target_distance=30 shaping=1"},
    )
    init_noise: float = field(default=1.0, metadata={"help": "start-state perturbation while training (0..1)"})
    max_time: float = field(default=40.0, metadata={"help": "episode time limit (s)"})
    # --- curriculum: these RewardConfig fields (w_fuel/w_time too) start at the given values and ramp
    # linearly to the run's values over the first curriculum_fraction of training
    curriculum_start: dict[str, float] = field(
        default_factory=lambda: {"target_distance": 2.0, "target_height": 2.0},
        metadata={"help": "start values, e.g. --curriculum-start target_distance=2 w_time=0.5"})
    curriculum_fraction: float = field(default=0.5, metadata={"help": "fraction of training the ramp lasts"})
    # --- PPO
    learning_rate: float = field(default=3e-4, metadata={"help": "Adam step size"})
    lr_schedule: str = field(default="linear", metadata={"help": "'constant' or 'linear' (decay to 0)"})
    n_steps: int = field(default=128, metadata={"help": "steps per loader per rollout"})
    batch_size: int = field(default=2048, metadata={"help": "minibatch size"})
    n_epochs: int = field(default=10, metadata={"help": "epochs over each rollout"})
    gamma: float = field(default=0.995, metadata={"help": "discount factor"})
    gae_lambda: float = field(default=0.95, metadata={"help": "GAE lambda"})
    clip_range: float = field(default=0.2, metadata={"help": "PPO clip range"})
    ent_coef: float = field(default=0.0, metadata={"help": "entropy bonus"})
    vf_coef: float = field(default=0.5, metadata={"help": "value loss weight"})
    max_grad_norm: float = field(default=0.5, metadata={"help": "gradient clipping"})
    target_kl: float | None = field(default=None, metadata={"help": "early stop of the epochs (none: off)"})
    net_arch: tuple[int, ...] = field(default=(64, 64), metadata={"help": "hidden layers of policy and value nets"})
    log_std_init: float = field(default=-0.5, metadata={"help": "initial log std of the Gaussian policy"})
    log_std_final: float | None = field(
        default=-2.0, metadata={"help": "anneal a cap on the log std linearly to this at the end (none: off)"})
    shift_bias_init: float = field(
        default=-1.0, metadata={"help": "initial mean of the shift action (< 0: hold the gear at first; "
                                "WheelLoaderTarget-v2 and v3 have none: their assist shifts)"})
    coast_bias_init: float = field(
        default=1.0, metadata={"help": "WheelLoaderTarget-v3: initial mean of the coasting fraction (+1: 0.95 of "
                               "the limit, no early coasting: v2's cycles at first)"})
    fuel_bias_init: float = field(
        default=0.0, metadata={"help": "initial mean of the fuel action (< 0: explore below the governor)"})
    bucket_bias_init: float = field(
        default=0.0, metadata={"help": "initial mean of the bucket action (> 0: lift from the start)"})
    bounded_mean: bool = field(
        default=False, metadata={"help": "squash the Gaussian's mean into [-1.1, 1.1] (BoundedMeanPolicy)"})
    use_sde: bool = field(default=False, metadata={"help": "generalized state-dependent exploration (gSDE)"})
    sde_sample_freq: int = field(default=-1, metadata={"help": "gSDE: resample the noise every n steps (-1: per rollout)"})
    norm_obs: bool = field(default=True, metadata={"help": "VecNormalize observations"})
    norm_reward: bool = field(default=True, metadata={"help": "VecNormalize rewards (by the return's std)"})
    # --- evaluation and checkpoints
    eval_freq: int = field(default=200_000, metadata={"help": "evaluate every this many steps"})
    eval_episodes: int = field(default=50, metadata={"help": "perturbed start states per evaluation"})
    eval_init_noise: float = field(default=1.0, metadata={"help": "init_noise of the evaluation episodes"})
    score: bool = field(default=True, metadata={"help": "score evaluations against the Pareto front (mpc)"})
    checkpoint_freq: int = field(default=500_000, metadata={"help": "checkpoint every this many steps"})
    keep_checkpoints: int = field(default=2, metadata={"help": "checkpoints kept on disk"})
    # --- behaviour-cloning regularization (DAPG-style: keeps a cloned policy near its expert while PPO tunes it)
    bc_demos: str = field(default="", metadata={
        "help": "folder of MPC demonstration episodes (scripts/train_bc.py) whose labels the actor is also fitted to "
                "before each rollout, target envs only ('': off)"})
    bc_weight: float = field(default=1.0, metadata={
        "help": "weight of the behaviour-cloning loss (the weighted squared error of the mean action) at the "
                "start, against PPO's loss; decays linearly to 0"})
    bc_fraction: float = field(default=1.0, metadata={"help": "fraction of training over which bc_weight decays to 0"})

    def __post_init__(self) -> None:
        """Every field checked for type and range (ConfigError naming it): a run with nonsense settings
        fails here, not hours later or silently."""
        cycle.check_braking(self.braking)
        for f in dataclasses.fields(self):  # (numpy's scalars as Python's: np.int64 seeds were refused)
            setattr(self, f.name, plain(getattr(self, f.name)))
        if isinstance(self.net_arch, (str, bytes)) or not hasattr(self.net_arch, "__iter__"):
            raise ConfigError("net_arch", _RULES["net_arch"][0], self.net_arch)
        self.net_arch = tuple(map(plain, self.net_arch))
        if isinstance(self.target, (str, bytes)) or not hasattr(self.target, "__iter__"):
            raise ConfigError("target", _RULES["target"][0], self.target)
        self.target = tuple(self.target)
        for name in ("reward", "curriculum_start"):
            value = getattr(self, name)
            if not isinstance(value, dict):
                raise ConfigError(name, _RULES[name][0], value)
            setattr(self, name, {str(k): v for k, v in value.items()})
        for name, (requirement, ok) in _RULES.items():
            if not ok(getattr(self, name)):
                raise ConfigError(name, requirement, getattr(self, name))
        # (SB3 asserted >= 2 with a traceback. A batch larger than the rollout takes the whole rollout, as SB3 says
        # in a warning: the default 2048 with --num-envs 1 does, so it is not refused.)
        if not 2 <= self.n_steps * self.num_envs <= MAX_ROLLOUT:
            raise ConfigError("n_steps", f"such that n_steps * num_envs lies in [2, {MAX_ROLLOUT}] (num_envs "
                              f"{self.num_envs})", self.n_steps)
        if self.scenario and self.env_id == "WheelLoader-v1":
            raise ConfigError("scenario", "'' with WheelLoader-v1 (it does not observe the scenario; use "
                              "WheelLoader-v2 or WheelLoaderTarget-v0/v1)", self.scenario)
        if self.bc_demos and self.env_id not in TARGET_ENV_IDS:
            raise ConfigError("bc_demos", f"'' with {self.env_id} (demonstrations are episodes of the target "
                              f"envs {', '.join(TARGET_ENV_IDS)})", self.bc_demos)
        self.target = tuple(float(x) for x in self.target)
        self.reward = {k: float(v) for k, v in self.reward.items()}
        self.curriculum_start = {k: float(v) for k, v in self.curriculum_start.items()}
        from wl_env.episode import RewardConfig

        unknown = (set(self.reward) | set(self.curriculum_start)) - set(RewardConfig.__dataclass_fields__)
        if unknown:
            raise ValueError(f"unknown RewardConfig field(s) {sorted(unknown)} (--reward, --curriculum-start); known: "
                             f"{sorted(RewardConfig.__dataclass_fields__)}")
        # (the run's w_fuel and w_time are their own fields, which the env applies over the reward's: --reward
        # w_fuel=0.5 trained with w_fuel 2.0, the default, and config.json recorded 0.5)
        shadowed = {k: v for k, v in self.reward.items() if k in ("w_fuel", "w_time") and v != getattr(self, k)}
        if shadowed:
            raise ConfigError("reward", "without w_fuel and w_time, which are fields of their own (--w-fuel, --w-time) "
                              f"that set them: give {', '.join(f'{k}={v:g}' for k, v in shadowed.items())} there",
                              self.reward)
        for name in ("reward", "curriculum_start"):  # (each field's range, now: not at the first reset)
            try:
                RewardConfig(**getattr(self, name))
            except ValueError as exc:
                raise ConfigError(name, f"RewardConfig fields in their ranges ({exc})", getattr(self, name)) from None

    @property
    def name(self) -> str:
        return self.run_name or f"ppo_{self.braking}_s{self.seed}"

    @property
    def run_dir(self) -> Path:
        return Path(self.log_dir) / self.name

    @property
    def targeted(self) -> bool:
        """Whether the run's env gives each episode a target cycle time (:data:`TARGETED_ENV_IDS`)."""
        return self.env_id in TARGETED_ENV_IDS

    def env_kwargs(self) -> dict[str, Any]:
        """Keyword arguments of the run's env (``env_id``, single or vector), without init_noise."""
        kwargs: dict[str, Any] = {"braking": self.braking, "max_time": self.max_time, "reward": dict(self.reward),
                                  "w_fuel": self.w_fuel, "w_time": 0.0 if self.targeted else self.w_time}
        if self.scenario:
            kwargs["scenario"] = self.scenario
        if self.targeted:
            kwargs["target"] = tuple(self.target)
            if self.target_power != 1.0:  # (the key only where it is used: older runs' kwargs stay the same)
                kwargs["target_power"] = float(self.target_power)
        return kwargs

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["net_arch"] = list(self.net_arch)
        d["target"] = list(self.target)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> PPOConfig:
        known = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in known})
