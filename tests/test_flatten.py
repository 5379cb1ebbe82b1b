"""The flattened float code (wl_env.physics.flatten) computes exactly what the code it was traced from does."""

import dataclasses
import math
import pickle

import numpy as np
import pytest

from wl_env.episode import CycleStepper, RewardConfig
from wl_env.params import DEFAULT_PARAMS as P
from wl_env.physics.backend import FLOAT_OPS, ops_for
from wl_env.physics.flatten import Sym, flatten
from wl_env.simulator import Simulator


def same(a, b):
    """Bit-identical, types included (repr tells -0.0 from 0.0 and True from 1)."""
    return repr(a) == repr(b)


def random_states(rng, n):
    for _ in range(n):
        yield (
            float(rng.choice([rng.uniform(1.0, 260.0), 57.0, P.omega_max])),
            float(rng.choice([rng.uniform(-3.5, 3.5), 0.0, -0.0])),
            float(rng.uniform(-1.0, 6.0)),  # beyond both end stops of the boom too
            float(rng.choice([rng.uniform(0.0, 1.5), 0.0])),
            float(rng.uniform(-15.0, 8.0)),
            float(rng.uniform(0.0, 0.2)),
        )


@pytest.mark.parametrize("braking", ["service", "tc"])
def test_flattened_simulator_equals_the_traced_code(braking):
    sim = Simulator(P, braking)
    controls, advance, _ = sim._flattened()
    rng = np.random.default_rng(0)
    for y in random_states(rng, 300):
        phase = int(rng.integers(1, 5))
        gear, d, brake = sim.phase_constants(phase)
        cmd = (float(rng.uniform(-50, 300)), float(rng.uniform(-3, 3)), float(rng.uniform(-1e3, 7e4)))
        h = float(rng.choice([0.1, 0.05, 0.013]))
        u = controls(y, gear, brake, *cmd, h)
        assert same(u, sim._controls(y, gear, brake, *cmd, h))
        assert same(advance(y, u[:3], gear, d, h), sim._advance(y, u[:3], gear, d, h))


@pytest.mark.parametrize("fuel_action", ["injection", "engine_speed"])  # (engine_speed: WheelLoaderTarget-v1's governor)
@pytest.mark.parametrize("substeps", [1, 3])
@pytest.mark.parametrize("braking", ["service", "tc"])
def test_flattened_step_equals_the_traced_code(braking, substeps, fuel_action):
    core = CycleStepper(P, braking, 0.1, substeps, 40.0, RewardConfig(), fuel_action=fuel_action)
    rng = np.random.default_rng(1)
    cut = 0
    for y in random_states(rng, 400):
        phase = int(rng.integers(1, 5))
        t, rev_err = float(rng.uniform(0, 40)), float(rng.choice([math.nan, rng.uniform(-1, 1)]))
        action = tuple(float(v) for v in rng.uniform(-1, 1, 4))
        through, cut_at_stop = (f(y, phase, t, rev_err, 0.1, action) for f in core._flatten_step()[:2])
        reference = core._step(y, phase, t, rev_err, 0.1, action)
        assert through is None or cut_at_stop is None  # each speculates on the other branch
        if through is None:  # the guard: a substep reached V = 0 and is cut there
            cut += 1
        flat = through if through is not None else cut_at_stop
        if flat is not None:
            assert same(flat, reference)
        assert same(core.step(y, phase, t, rev_err, 0.1, action), reference)
    assert cut > 0  # the fallback was exercised


def test_reconfiguration_discards_the_flattened_code():
    core = CycleStepper(P, "service", 0.1, 1, 40.0, RewardConfig())
    y, action = (P.omega_0, 0.0, P.H_0, 0.0, 0.0, 0.0), (1.0, 0.2, -1.0, -1.0)
    before = core.step(y, 1, 0.0, math.nan, 0.0, action)["reward"]
    core.reward = dataclasses.replace(core.reward, w_time=5.0)  # e.g. a reward curriculum
    after = core.step(y, 1, 0.0, math.nan, 0.0, action)
    assert after["reward"] != before and same(after, core._step(y, 1, 0.0, math.nan, 0.0, action))
    core.sim.params = P.replace(M_load=2000.0)  # the simulator's parameters, behind the stepper's back
    lighter = core.step(y, 1, 0.0, math.nan, 0.0, action)
    assert lighter["y"] != after["y"] and same(lighter, core._step(y, 1, 0.0, math.nan, 0.0, action))


def test_steppers_with_flattened_code_pickle():
    core = CycleStepper(P, "tc", 0.1, 1, 40.0, RewardConfig())
    y, action = (P.omega_0, -1.0, 2.0, 0.1, -2.0, 0.01), (0.5, 0.2, -1.0, 1.0)
    r = core.step(y, 1, 0.0, math.nan, 0.0, action)
    copy = pickle.loads(pickle.dumps(core))
    assert same(copy.step(y, 1, 0.0, math.nan, 0.0, action), r)


def test_primitives_keep_float_semantics():
    ops = FLOAT_OPS

    def f(a, b):
        o = ops_for(a)
        assert o is not FLOAT_OPS
        return o.fmin(a, b), o.fmax(a, b), o.clip(a, -1.0, b), o.where(a < b, a, b), o.sqrt(abs(b)), -a / b

    flat = flatten(f, "a", "b")
    values = [-2.0, -0.0, 0.0, 0.5, 3.0, math.inf, -math.inf, math.nan]
    for a in values:
        for b in values:
            try:
                expected = (
                    ops.fmin(a, b),
                    ops.fmax(a, b),
                    ops.clip(a, -1.0, b),
                    ops.where(a < b, a, b),
                    ops.sqrt(abs(b)),
                    -a / b,
                )
            except ZeroDivisionError:
                with pytest.raises(ZeroDivisionError):
                    flat(a, b)
                continue
            assert same(flat(a, b), expected)


def test_python_branches_are_refused_unless_speculating():
    def branchy(x):
        return x if x > 0.0 else -x

    with pytest.raises(TypeError, match="ops.where"):
        flatten(branchy, "x")
    guarded = flatten(branchy, "x", speculate=False)  # traced along x > 0.0 being false
    assert guarded(-2.0) == 2.0 and guarded(3.0) is None
    taken = flatten(branchy, "x", speculate=True)  # ... and along it being true
    assert taken(3.0) == 3.0 and taken(-2.0) is None
    assert isinstance(Sym.OPS.fmin(1.0, 2.0), float)  # constants are folded at trace time


def test_cache_key_changes_with_every_configuration_attribute():
    """The flattened code's cache key is derived from everything the step reads: changing any attribute of
    the stepper, its simulator or its codec (even one added later) gives another key and other code."""
    from wl_env.physics.flatten import config_key

    core = CycleStepper(P, "service", 0.1, 1, 40.0, RewardConfig())
    base = config_key(core)
    owners = [core, core.sim, core.codec]
    n_checked = 0
    for owner in owners:
        for name, value in list(vars(owner).items()):
            if name == "_flat" or not isinstance(value, (int, float)) or isinstance(value, bool):
                continue
            object.__setattr__(owner, name, value * 1.5 + 0.25)
            assert config_key(core) != base, f"{type(owner).__name__}.{name} is not in the key"
            object.__setattr__(owner, name, value)
            n_checked += 1
    core.sim.new_attribute = 1.0  # an attribute a later change adds to the step
    assert config_key(core) != base
    del core.sim.new_attribute
    assert config_key(core) == base and n_checked >= 4
    # parameters and reward weights are in it too: other values, other generated code
    other = CycleStepper(P.replace(M_load=9000.0), "service", 0.1, 1, 40.0, RewardConfig())
    assert config_key(other) != base
    assert core._flatten_step()[0] is not other._flatten_step()[0]
