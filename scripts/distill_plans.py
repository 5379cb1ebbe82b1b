"""Expert iteration for a plan policy (``WheelLoaderPlan-v0`` or ``-v1``): improve it by search, then learn the search.

    python scripts/distill_plans.py --policy agents/policies/plan_target_service --out runs/distilled_service \
        [--cycles 1024 --population 16 --generations 20 --sigma 0.15 --seed 0]

1. **Search.** On ``--cycles`` fresh draws of the policy's own training distribution (its `train` scenarios,
   start states and target ratios, from its config), CMA-ES (pycma) searches the 14 plan numbers of each
   cycle, started at the policy's plan, for the policy's own training reward (the plan env's return: fuel,
   lateness, targets, violations). ``--batch`` searches share one vector env, each in ``--population``
   loaders that run the same cycle (the same reset seed). A plan replaces the policy's only if its cycle
   succeeded without violation and returned more.
2. **Distil.** The policy's mean is fitted to the plans found (mean squared error, Adam, the last 10 % of the
   cycles held out; the weights of the best held-out epoch are kept). Its value network and its
   observation normalization are left as they were.
3. **Check.** The policy before and after run ``--eval-cycles`` other fresh draws; both returns are printed and
   recorded in the new policy's metadata (``distillation``).

Nothing here reads the ``test`` suite. The searches are written to ``--demos`` (default ``<out>_searches.npz``)
after each batch: a stopped run resumes there with the same options (a file from other options is refused).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from agents.evaluate import policy_input_files
from agents.policy_files import PolicyFiles, check_policy_output
from agents.train_cli import tyro_options
from wl_env.atomic_io import atomic_path, check_not_an_input, check_output_file
from wl_env.logs import run_script

log = logging.getLogger("distill_plans")

# the options that define the searches (a resumed --demos file must have been written with the same)
SEARCH_OPTIONS = ("cycles", "batch", "population", "generations", "sigma", "seed")
SEED_STRIDE = 1_000_000  # cycle c of --seed s resets with seed s * SEED_STRIDE + c; the checks use c >= --cycles
MAX_CYCLES = 10**6
# (its CMA-ES seeds s * SEED_STRIDE + c + 1, c < --cycles, within pycma's 2**32 - 1: --seed 5000 failed at the first search)
MAX_SEED = (2**32 - 1 - MAX_CYCLES) // SEED_STRIDE


@dataclass
class Options:
    policy: str  # a pickle-free plan policy (its stem, files or run folder)
    out: Path  # stem of the distilled policy (<out>.safetensors, <out>_vecnormalize.npz, <out>.json)
    cycles: int = 1024  # training cycles searched
    batch: int = 16  # searches per vector env
    population: int = 16  # CMA-ES population (loaders per search)
    generations: int = 20
    sigma: float = 0.15  # CMA-ES initial step, in the action space's units ([-1, 1] per plan number)
    seed: int = 0
    epochs: int = 300
    learning_rate: float = 1e-4
    minibatch: int = 128
    eval_cycles: int = 512  # fresh cycles on which the policy before and after is checked
    demos: Path | None = None  # the searches (default <out>_searches.npz)


def check(o: Options) -> None:
    """ValueError naming the option and its range (before any work)."""
    for name, lo, hi in (("cycles", 2, MAX_CYCLES), ("batch", 1, 4096), ("population", 4, 4096), ("generations", 1, 10**4),
                         ("epochs", 0, 10**6), ("minibatch", 1, 10**6), ("eval_cycles", 1, 10**6),
                         ("seed", 0, MAX_SEED)):
        v = getattr(o, name)
        if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
            raise ValueError(f"--{name.replace('_', '-')} must be an integer in [{lo}, {hi}], got {v!r}")
    if o.cycles % o.batch:
        raise ValueError(f"--cycles ({o.cycles}) must be a multiple of --batch ({o.batch})")
    if not 0.0 < o.sigma <= 1.0:
        raise ValueError(f"--sigma must lie in (0, 1] (action units), got {o.sigma!r}")
    if not 0.0 < o.learning_rate <= 1.0:
        raise ValueError(f"--learning-rate must lie in (0, 1], got {o.learning_rate!r}")
    if not Path(o.out).name.strip() or Path(o.out).name in (".", ".."):  # ("" passed as the file ".json", and failed
        raise ValueError(f"--out must name the policy's file stem (PATH/NAME), got {str(o.out)!r}")  # after the work)
    check_policy_output(o.out, "--out")  # (each of its files: a folder at OUT.safetensors failed after the work)
    # the searches file, the default too (a FIFO at OUT_searches.npz hung the resume's read for good), and none of the
    # policy's files (--demos OUT.json: the searches, then the policy written over them)
    demos = o.demos if o.demos is not None else Path(f"{o.out}_searches.npz")
    check_output_file(demos, "--demos" if o.demos is not None else "--demos (default OUT_searches.npz)")
    from wl_env.atomic_io import refuse_one_path_twice

    out_files = dataclasses.astuple(PolicyFiles.of(o.out))  # (the files write_policy writes)
    refuse_one_path_twice([*(("--out", path) for path in out_files), ("--demos", demos)])
    # (--out P of --policy P wrote the distilled policy over the one it distils, after the work)
    inputs = policy_input_files(o.policy)
    for path in out_files:
        check_not_an_input(path, inputs, "--out")
    check_not_an_input(demos, inputs, "--demos")


def plan_env(config: Any, num_envs: int):
    """The plan policy's training env (its config's scenario source, targets and reward), ``num_envs`` loaders."""
    import gymnasium as gym

    import wl_env  # noqa: F401  (registers the envs)

    return gym.make_vec(config.env_id, num_envs=num_envs, vectorization_mode="vector_entry_point",
                        **config.env_kwargs())


def run_plans(env: Any, seeds: list[int], plans: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """Each loader's cycle from its reset seed under its plan: (observation at the start, return, success
    without violation, info)."""
    obs, _ = env.reset(seed=seeds)
    _, reward, _, _, info = env.step(plans)
    return obs, np.asarray(reward, float), info["is_success"] & (info["violation"] <= 0.0), info


@dataclass
class Searches:
    """One row per searched cycle: its start observation, the policy's plan and the best plan found, and
    their returns (the policy's training reward)."""

    obs: np.ndarray
    policy_plan: np.ndarray
    best_plan: np.ndarray
    policy_return: np.ndarray
    best_return: np.ndarray

    FIELDS = ("obs", "policy_plan", "best_plan", "policy_return", "best_return")

    @classmethod
    def empty(cls, n_obs: int, n_act: int) -> Searches:
        return cls(np.zeros((0, n_obs), np.float32), np.zeros((0, n_act)), np.zeros((0, n_act)), np.zeros(0), np.zeros(0))

    def extend(self, other: Searches) -> Searches:
        return Searches(*(np.concatenate([getattr(self, f), getattr(other, f)]) for f in self.FIELDS))

    def save(self, path: Path, key: dict[str, Any]) -> None:
        with atomic_path(path, ".npz") as tmp:
            np.savez(tmp, key=np.array(json.dumps(key, sort_keys=True)), **{f: getattr(self, f) for f in self.FIELDS})

    @classmethod
    def load(cls, path: Path, key: dict[str, Any], n_obs: int, n_act: int) -> Searches:
        """The searches in ``path`` (no pickle), refused unless written with the same ``key`` and shapes."""
        try:
            with np.load(path, allow_pickle=False) as z:
                written = json.loads(str(z["key"]))
                s = cls(*(np.array(z[f]) for f in cls.FIELDS))
        except (OSError, ValueError, KeyError) as exc:
            raise ValueError(f"--demos {path}: not a searches file of this script ({exc})") from None
        if written != key:
            raise ValueError(f"--demos {path} was written by other options or another policy ({written}); "
                             f"give another --demos or remove it")
        n = len(s.obs)
        shapes_ok = s.obs.shape == (n, n_obs) and all(getattr(s, f).shape == (n, n_act) for f in ("policy_plan", "best_plan"))
        if not (shapes_ok and s.policy_return.shape == s.best_return.shape == (n,)
                and all(np.all(np.isfinite(getattr(s, f))) for f in cls.FIELDS)):
            raise ValueError(f"--demos {path}: arrays of the wrong shape or not finite")
        return s


def search_batch(env: Any, policy: Any, first: int, o: Options) -> Searches:
    """CMA-ES on cycles ``first`` .. ``first + o.batch - 1``, each from the policy's plan."""
    import cma

    P = o.population
    seeds = [o.seed * SEED_STRIDE + first + k for k in range(o.batch) for _ in range(P)]
    obs, _ = env.reset(seed=seeds)
    start = obs[::P]
    if not np.allclose(obs.reshape(o.batch, P, -1), start[:, None, :]):
        raise RuntimeError("loaders reset with one seed started different cycles")  # (the search's premise)
    x0 = np.clip(policy.act(start).astype(float), -1.0, 1.0)
    _, r0, ok0, _ = run_plans(env, seeds, np.repeat(x0, P, axis=0))
    r0 = r0[::P]
    best, best_r = x0.copy(), np.where(ok0[::P], r0, -np.inf)
    strategies = [cma.CMAEvolutionStrategy(x0[k], o.sigma, {"bounds": [-1, 1], "popsize": P, "verbose": -9,
                                                            "seed": o.seed * SEED_STRIDE + first + k + 1})
                  for k in range(o.batch)]
    for _ in range(o.generations):
        asked = [np.array(es.ask()) for es in strategies]
        _, r, ok, _ = run_plans(env, seeds, np.concatenate(asked))
        for k, es in enumerate(strategies):
            rk, okk = r[k * P:(k + 1) * P], ok[k * P:(k + 1) * P]
            es.tell(list(asked[k]), list(-rk))
            j = int(np.argmax(np.where(okk, rk, -np.inf)))
            if okk[j] and rk[j] > best_r[k]:
                best[k], best_r[k] = asked[k][j], rk[j]
    found = np.isfinite(best_r)  # (a cycle where nothing succeeded keeps the policy's plan and return)
    return Searches(start.astype(np.float32), x0, best, r0, np.where(found, best_r, r0))


def fit(policy: Any, s: Searches, o: Options) -> dict[str, float]:
    """Fit the policy's Gaussian mean to the best plans (in place); the held-out 10 % picks the epoch."""
    import copy

    import torch as th

    th.manual_seed(o.seed)
    net = policy.network
    n_val = max(1, len(s.obs) // 10)
    x = th.as_tensor(policy.normalize(s.obs))
    y = th.as_tensor(s.best_plan, dtype=th.float32)
    x_tr, y_tr, x_val, y_val = x[:-n_val], y[:-n_val], x[-n_val:], y[-n_val:]
    actor = [*net.mlp_extractor.policy_net.parameters(), *net.action_net.parameters()]
    opt = th.optim.Adam(actor, lr=o.learning_rate)

    def loss_of(xb: Any, yb: Any) -> Any:
        diff = net.get_distribution(xb).distribution.mean - yb
        # a plan at a bound of the action space is met by any mean beyond it (the env clips)
        beyond = ((yb >= 1.0 - 1e-6) & (diff > 0)) | ((yb <= -1.0 + 1e-6) & (diff < 0))
        return th.where(beyond, th.zeros_like(diff), diff).pow(2).mean()

    with th.no_grad():
        val0 = best_val = float(loss_of(x_val, y_val))
    best_state, best_epoch = copy.deepcopy(net.state_dict()), 0
    gen = th.Generator().manual_seed(o.seed)
    net.train()
    for epoch in range(1, o.epochs + 1):
        for idx in th.randperm(len(x_tr), generator=gen).split(o.minibatch):
            opt.zero_grad()
            loss_of(x_tr[idx], y_tr[idx]).backward()
            opt.step()
        with th.no_grad():
            val = float(loss_of(x_val, y_val))
        if val < best_val:
            best_val, best_state, best_epoch = val, copy.deepcopy(net.state_dict()), epoch
    net.load_state_dict(best_state)
    net.eval()
    return {"validation_mse_before": val0, "validation_mse_after": best_val, "best_epoch": best_epoch}


def fresh_draw_scores(env: Any, policy: Any, o: Options) -> dict[str, float]:
    """The policy's plans on ``o.eval_cycles`` fresh draws (cycles after the searched ones): mean return,
    success rate (no violation) and the median lateness."""
    n = env.unwrapped.num_envs
    returns, oks, late = [], [], []
    for first in range(o.cycles, o.cycles + o.eval_cycles, n):
        seeds = [o.seed * SEED_STRIDE + first + i for i in range(n)]
        obs, _ = env.reset(seed=seeds)
        _, r, ok, info = run_plans(env, seeds, np.clip(policy.act(obs), -1.0, 1.0))
        k = min(n, o.cycles + o.eval_cycles - first)
        returns += list(r[:k])
        oks += list(ok[:k])
        late += list(np.maximum(info["t"][:k] - info["target_time"][:k], 0.0) / info["target_time"][:k])
    return {"mean_return": float(np.mean(returns)), "success_rate": float(np.mean(oks)),
            "lateness_median": float(np.median(late))}


def main(o: Options) -> dict[str, Any]:
    check(o)
    from agents.policy_files import write_policy
    from agents.ppo import load_policy
    from agents.ppo_config import PLAN_ENV_IDS, PPOConfig

    policy = load_policy(o.policy)
    if policy.env_id not in PLAN_ENV_IDS:
        raise ValueError(f"--policy {o.policy} acts on {policy.env_id}; distillation takes a plan policy "
                         f"({', '.join(PLAN_ENV_IDS)})")
    config = PPOConfig.from_dict(policy.meta["config"])
    n_obs, n_act = policy.network.observation_space.shape[0], policy.network.action_space.shape[0]
    demos = o.demos or Path(f"{o.out}_searches.npz")
    key = {"policy_weights_sha256": policy.meta["files"]["weights"]["sha256"], **{k: getattr(o, k) for k in SEARCH_OPTIONS}}
    searches = Searches.load(demos, key, n_obs, n_act) if demos.exists() else Searches.empty(n_obs, n_act)
    t0 = time.perf_counter()
    env = plan_env(config, o.batch * o.population)
    if len(searches.obs):
        log.info("resuming from %s: %d of %d cycles searched", demos, len(searches.obs), o.cycles)
    for first in range(len(searches.obs), o.cycles, o.batch):
        searches = searches.extend(search_batch(env, policy, first, o))
        searches.save(demos, key)
        gain = searches.best_return - searches.policy_return
        log.info("%d / %d cycles searched: return %+.3f -> %+.3f (mean), improved on %.0f %%", len(searches.obs),
                 o.cycles, searches.policy_return.mean(), searches.best_return.mean(), 100 * np.mean(gain > 0))
    search_s = time.perf_counter() - t0
    fresh_env = plan_env(config, min(256, o.eval_cycles))
    before = fresh_draw_scores(fresh_env, policy, o)
    t1 = time.perf_counter()
    fitted = fit(policy, searches, o)
    after = fresh_draw_scores(fresh_env, policy, o)
    record = {"options": {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(o).items()},
              "searched": {"cycles": len(searches.obs), "mean_policy_return": float(searches.policy_return.mean()),
                           "mean_best_return": float(searches.best_return.mean()),
                           "improved_fraction": float(np.mean(searches.best_return > searches.policy_return))},
              "fit": fitted, "check_before": before, "check_after": after,
              "search_wall_time_s": round(search_s, 1), "fit_wall_time_s": round(time.perf_counter() - t1, 1)}
    log.info("check on %d fresh cycles: return %+.3f -> %+.3f, success %.3f -> %.3f, median lateness %.4f -> %.4f",
             o.eval_cycles, before["mean_return"], after["mean_return"], before["success_rate"],
             after["success_rate"], before["lateness_median"], after["lateness_median"])
    meta = {k: v for k, v in policy.meta.items() if k not in ("evaluation", "name")}
    meta.update(name=Path(o.out).name, distillation=record,
                training_wall_time_s=round(float(meta.get("training_wall_time_s") or 0.0) + search_s
                                           + record["fit_wall_time_s"], 1))
    write_policy(policy.network, policy.normalization, o.out, meta)
    print(json.dumps(record, indent=1))
    return record


if __name__ == "__main__":
    run_script("distill_plans", lambda: main(tyro_options(Options)))
