"""Determinism audit (stop 64): results that depended on the process's history or on OS entropy, not on the seed."""

import hashlib

import gymnasium as gym
import numpy as np
from fakes import tiny_ppo_config

import wl_env  # noqa: F401  (registers the ids)


def test_a_none_in_a_vector_reset_seed_list_continues_that_loaders_generator():
    """``reset(seed=[s, None])`` after a seeded reset gave loader 1 a fresh generator from OS entropy: its next
    scenario (a suite's draw) differed between two envs built and seeded alike, and from the single env's
    ``reset()`` after ``reset(seed=20)``, which continues the seed's generator (Gymnasium's semantics)."""

    def resets():
        venv = gym.make_vec("WheelLoader-v2", num_envs=2, vectorization_mode="vector_entry_point", scenario="train",
                            init_noise=0.5)
        first, _ = venv.reset(seed=[10, 20])
        again, _ = venv.reset(seed=[11, None])
        return first, again

    (first_a, again_a), (_, again_b) = resets(), resets()
    np.testing.assert_array_equal(again_a, again_b)
    single = gym.make("WheelLoader-v2", scenario="train", init_noise=0.5)
    np.testing.assert_array_equal(single.reset(seed=20)[0], first_a[1])
    np.testing.assert_array_equal(single.reset()[0], again_a[1])
    np.testing.assert_array_equal(single.reset(seed=11)[0], again_a[0])


def test_the_same_cycle_planned_again_in_a_process_drives_as_the_first():
    """A cycle the process had planned before was solved again from its stored first plan, which gave that plan
    to the solver's tolerance only: the nominal service cycle at minimum time drove 85.56 g the second time in a
    process, 85.66 g the first time (and in a fresh process), its states up to 2.3 apart. The synchronous controller
    now plans afresh (the real-time one, whose plans depend on timing anyway, still starts from the stored plan)."""
    from mpc.controller.mpc import MPCConfig, MPCController, forget_plans
    from wl_env.rollout import run_episode

    forget_plans()  # (the first cycle below plans as a fresh process does)
    runs, sources = [], []
    for _ in range(2):
        ctrl = MPCController("service", config=MPCConfig(mode="time"))
        runs.append(run_episode(gym.make("WheelLoader-v2", braking="service"), ctrl, seed=0,
                                trajectory=True).to_dict(trajectory=True))
        sources.append(ctrl.first_plan_from)
    assert sources == ["reference", "reference"]
    assert runs[0] == runs[1]


def test_a_training_gives_the_same_policy_whatever_the_process_trained_before(tmp_path):
    """Two trainings with the same seed in one process, another seed's between them, write the same weights and
    normalization (a sweep trains its runs one after another in one process, or each in its own)."""
    from agents.ppo import train

    digests = []
    for i, seed in enumerate((3, 4, 3)):
        cfg = tiny_ppo_config(tmp_path, total_timesteps=1024, eval_freq=10**6, eval_episodes=0, checkpoint_freq=10**6,
                              seed=seed, run_name=f"r{i}")
        train(cfg)
        final = tmp_path / f"r{i}" / "final"
        digests.append(tuple(hashlib.sha256((final / name).read_bytes()).hexdigest()
                             for name in ("policy.safetensors", "policy_vecnormalize.npz")))
    assert digests[0] == digests[2] and digests[0] != digests[1]
