"""``WheelLoader-v2`` (and ``-v1``): a wheel loader driving the short loading cycle of a scenario."""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from wl_env import cycle
from wl_env.assist import N_ASSIST_ACTIONS, N_COAST_ACTIONS, assisted_action
from wl_env.codec import TARGET_OBS_HIGH, TARGET_OBS_LOW, TIME_SCALE
from wl_env.episode import CycleStepper, RewardConfig
from wl_env.params import LoaderParams, check_flag, check_no_overridden, is_finite, plain, resolve_machine, shown
from wl_env.scenario import Scenario, is_file, resolve_scenario
from wl_env.suites import SUITES, Suite, load_suite


def scenario_source(scenario: Scenario | dict | str | None, braking: str | None,
                    machine: LoaderParams | None = None) -> tuple[Scenario | Suite | None, str]:
    """(a fixed Scenario, a Suite to draw from, or None for the given params; the braking alternative). A suite
    is checked against ``machine``, if given: each of its cycles must fit it (:meth:`Suite.check_machine`)."""
    if braking is not None:  # (not `braking or "service"`: a falsy braking such as "" or {} is an error)
        braking = cycle.check_braking(braking)
    if isinstance(scenario, str) and scenario in SUITES:
        suite, braking = load_suite(scenario), braking or "service"
        if machine is not None:
            suite.check_machine(machine, braking)
        return suite, braking
    if scenario is None:
        return None, braking or "service"
    if isinstance(scenario, str) and not scenario.strip().startswith(("{", "[")) and not is_file(scenario):
        raise ValueError(f"scenario must be a suite name {SUITES}, a Scenario, a dict of its fields, JSON text or a "
                         f"JSON file, got {shown(scenario)}")
    s = resolve_scenario(scenario, braking)
    return s, s.braking


def start_scenario(params: LoaderParams, braking: str, omega: float, H: float) -> Scenario | None:
    """The scenario an episode runs from its actual start (omega rad/s, H m), or None outside the ranges."""
    try:
        return Scenario.from_params(params.replace(omega_0=omega, H_0=H), braking)
    except ValueError:
        return None


def action_array(action: Any, name: str) -> np.ndarray:
    """``action`` as a float64 array if it holds real numbers (bool, int, float); ValueError naming ``name``
    otherwise (strings, complex numbers, objects, ints too large for a float: no silent casts)."""
    if type(action) is np.ndarray and action.dtype.kind == "f":  # (the common case, first: a step's hot path)
        return np.asarray(action, dtype=np.float64)
    if isinstance(action, np.ma.MaskedArray) and np.ma.is_masked(action):  # (asarray read a masked entry's filler)
        raise ValueError(f"{name} must be finite numbers in [-1, 1], got a masked array with {np.ma.count_masked(action)} masked entries")
    try:
        a = np.asarray(action)
    except (ValueError, TypeError):  # ragged nesting
        a = None
    if a is None or a.dtype.kind not in "biuf":
        raise ValueError(f"{name} must be finite numbers in [-1, 1], got {shown(action)}")
    return a.astype(np.float64)


TARGET_RATIOS = (1.0, 2.5)  # the target env's default: targets drawn from T_min (fastest) to ~the minimum-fuel end


def check_target_ratios(target: Any, name: str = "target") -> tuple[float, float]:
    """A target ratio to T_min (one number) or a range to draw from uniformly, within [1, 3]; ``name`` is
    the parameter the error names (``target``, or reset's option ``target_ratio``)."""
    target = plain(target) if not isinstance(target, (tuple, list)) else type(target)(map(plain, target))
    lo, hi = (target, target) if isinstance(target, (int, float)) and not isinstance(target, bool) else (
        tuple(target) if isinstance(target, (tuple, list)) and len(target) == 2 else (None, None))
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and is_finite(v) and 1.0 <= v <= 3.0
               for v in (lo, hi)) or lo > hi:
        raise ValueError(f"{name} must be a ratio to T_min in [1, 3] or a range (lo, hi) within it, got {shown(target)}")
    return float(lo), float(hi)


def check_assist(assist: Any, fuel_action: str, coast: Any = False, guards: Any = False, lift_floor: Any = False,
                 lift_off_load: Any = False, step_braking: Any = False) -> bool:
    """The driving assist (:mod:`wl_env.assist`) drives through the engine-speed governor; its coasting
    variant (``coast``, WheelLoaderTarget-v3), its guards (``guards``, v4), the lift's engine floor
    (``lift_floor``, v5) and the lift-off's full load (``lift_off_load``, v6: a variant of the guards) need it."""
    flags = (("coast", coast), ("guards", guards), ("lift_floor", lift_floor), ("lift_off_load", lift_off_load),
             ("step_braking", step_braking))
    for name, v in (("assist", assist), *flags):
        check_flag(name, v)
    for name, v in flags:
        if v and not assist:
            raise ValueError(f"{name}=True needs assist=True (it is a variant of the stopping assist)")
    if lift_off_load and not guards:
        raise ValueError("lift_off_load=True needs guards=True (it widens the guards' TC lift)")
    if assist and not (isinstance(fuel_action, str) and fuel_action == "engine_speed"):  # (an array: "ambiguous")
        raise ValueError(f"assist=True needs fuel_action='engine_speed' (its first action is a speed request), "
                         f"got fuel_action={shown(fuel_action)}")
    return assist


def n_actions(assist: bool, coast: bool) -> int:
    """The action count: the machine's 4, the assisted driver's 3, or 4 with the coasting fraction (coast)."""
    return N_COAST_ACTIONS if coast else N_ASSIST_ACTIONS if assist else 4


MIN_TARGET_TIME = 1.0  # s: far below any cycle (its lateness then stays finite; a target of 5e-324 s made it inf)


def check_target_time(target_time: Any, name: str = "target_time") -> float:
    """A target cycle time in [1, 40) s (the episode ends at 40 s), as a float; ValueError naming it (``name``)
    otherwise."""
    target_time = plain(target_time)
    if not (isinstance(target_time, (int, float)) and not isinstance(target_time, bool) and is_finite(target_time)
            and MIN_TARGET_TIME <= target_time < TIME_SCALE):
        raise ValueError(f"{name} must lie in [{MIN_TARGET_TIME:g}, {TIME_SCALE:g}) s (the episode ends at "
                         f"{TIME_SCALE:g} s; the shortest cycle of the scenario ranges takes ~5.7 s), "
                         f"got {shown(target_time)}")
    return float(target_time)


TARGET_POWER_RANGE = (0.25, 4.0)


def check_target_power(power: Any) -> float:
    """The exponent of the target ratio's draw: lo + (hi - lo) u**power, u uniform in [0, 1); 1 draws
    uniformly, above 1 favours the fast end (a training choice: the range stays the same)."""
    power, (lo, hi) = plain(power), TARGET_POWER_RANGE
    if isinstance(power, bool) or not (isinstance(power, (int, float)) and is_finite(power) and lo <= power <= hi):
        raise ValueError(f"target_power must be a number in [{lo:g}, {hi:g}], got {shown(power)}")
    return float(power)


def check_target_cycle(observe_target: bool, source: Any, machine: LoaderParams, braking: str) -> None:
    """A target env without a scenario or suite runs the machine's own cycle: its T_min is estimated within the
    scenario ranges only (:mod:`wl_env.suites.min_time`), so a cycle outside them is refused now, naming the
    field, not at the first reset."""
    if observe_target and source is None:
        try:
            Scenario.from_params(machine, braking)
        except ValueError as exc:
            raise ValueError(f"observe_target: the machine's cycle lies outside the scenario ranges, where no T_min "
                             f"estimate sets a target: {exc}") from None


def episode_target(scenario: Scenario | None, ratios: tuple[float, float], rng: np.random.Generator,
                   target_time: float | None = None, target_ratio: float | None = None,
                   power: float = 1.0) -> tuple[float, float]:
    """(the scenario's estimated T_min, the episode's target time) in s: ``target_time``, or
    ``target_ratio`` (default: drawn from ``ratios``, by :func:`check_target_power`'s ``power``) times the
    estimate (:mod:`wl_env.suites.min_time`)."""
    from wl_env.suites.min_time import estimate_min_time

    if scenario is None:
        raise ValueError("a target cycle time needs the episode's scenario within the scenario ranges")
    T_min = estimate_min_time(scenario)
    if target_time is not None and target_ratio is not None:
        raise ValueError("give the option target_time or target_ratio, not both")
    if target_time is not None:
        return T_min, check_target_time(target_time)
    if target_ratio is not None:
        lo, hi = check_target_ratios(target_ratio, "target_ratio")
    else:
        lo, hi = ratios
    if lo == hi:
        return T_min, float(T_min * lo)
    # (power 1 keeps the uniform draw's exact numbers)
    ratio = rng.uniform(lo, hi) if power == 1.0 else lo + (hi - lo) * float(rng.uniform()) ** power
    return T_min, float(T_min * ratio)


def target_features(target_time: Any, min_time: Any) -> tuple[Any, Any]:
    """WheelLoaderTarget's two observation entries: the target / 40 s and its ratio to the estimated T_min, less 1."""
    return target_time / TIME_SCALE, target_time / min_time - 1.0


def lateness_charge(t0: Any, t1: Any, target_time: Any, weight: float) -> Any:
    """The reward's lateness term for a step from t0 to t1 (s): ``weight`` per unit of (t - T) / T past the
    target, as it accrues (the episode's total is weight times its lateness)."""
    return weight * (np.maximum(t1 - target_time, 0.0) - np.maximum(t0 - target_time, 0.0)) / target_time


def make_reward_config(reward: RewardConfig | dict | None, w_fuel: float | None, w_time: float | None) -> RewardConfig:
    """A RewardConfig from a config, a dict of fields or None, with the weight shortcuts applied."""
    if reward is None:
        reward = RewardConfig()
    elif isinstance(reward, dict):
        known = set(RewardConfig.__dataclass_fields__)
        unknown = set(reward) - known
        if unknown:  # (as text: a key that is no string, beside one that is, failed in sorted() with a TypeError)
            raise ValueError(f"unknown reward field(s) {shown(sorted(unknown, key=repr), 200)}; known: {sorted(known)}")
        reward = RewardConfig(**reward)
    elif not isinstance(reward, RewardConfig):
        raise ValueError(f"reward must be a RewardConfig, a dict or None, got {type(reward).__name__}")
    changes = {k: v for k, v in (("w_fuel", w_fuel), ("w_time", w_time)) if v is not None}
    if changes:
        import dataclasses

        reward = dataclasses.replace(reward, **changes)
    return reward


class WheelLoaderEnv(gym.Env):
    """A wheel loader in the short loading cycle of a scenario: reverse from the pile while lifting the load
    (6.6 m in the paper's cycle), brake, stop, drive forward to the truck (6.6 m), brake and stop with the
    bucket raised to the dump height (5 m).

    ``scenario`` (:class:`wl_env.scenario.Scenario`, a dict of its fields, or a suite name of
    :mod:`wl_env.suites`, drawn from at each reset with the env's seeded generator) sets the payload, the
    distances, the rolling resistance, the dump height and the start state on the machine ``params``;
    ``reset(options={"scenario": ...})`` sets one episode's. ``info["scenario"]`` is the episode's scenario
    with its actual start (None if that lies outside the scenario ranges).

    The plant is the model of Nezhadali & Eriksson (diesel engine, torque converter, gearbox, hydraulic
    lift; 4 states), integrated with RK4 (``dt`` control interval, ``substeps`` per interval). The cycle
    has four phases with fixed gears (Table II); ``braking="service"`` stops the reversing machine with
    the service brakes in neutral, ``braking="tc"`` with the torque converter (forward gear while still
    reversing, TC mode I).

    ## Action Space

    ``Box(-1, 1, (4,), float32)``, mapped affinely onto the physical ranges:

    | Num | Action                         | -1          | +1                  |
    |-----|--------------------------------|-------------|---------------------|
    | 0   | fuel injection U_mf            | 0 mg/cycle  | U_mf_max (260 mg)   |
    | 1   | bucket vertical acceleration   | -2.5 m/s^2  | +2.5 m/s^2          |
    | 2   | service brake torque U_b       | 0 N m       | U_b_max (57 800 N m)|
    | 3   | shift request                  | hold        | > 0: end phase 1 or 3 |

    The brake acts only in the phases that use it (phase 2 with service braking, phase 4). Phase 2 ends
    by itself at the reversing point (V = 0). Values outside [-1, 1] are clipped; NaN raises.

    WheelLoaderTarget-v2 (``assist=True``): ``Box(-1, 1, (3,), float32)``, a driver's actions through the
    stopping assist (:mod:`wl_env.assist`, the rule-based operator's laws), which computes the 4 above:

    | Num | Action                                   | -1                    | +1                  |
    |-----|------------------------------------------|-----------------------|---------------------|
    | 0   | engine-speed request (as v1's action 0)  | omega_min + 5 rad/s   | omega_max           |
    | 1   | bucket acceleration asked (capped by the curve that stops the bucket at the dump height) | -2.5 m/s^2 | +2.5 m/s^2 |
    | 2   | braking deceleration, of the 0.18 g limit (sets where the legs end) | 50 % | 95 % |

    The assist ends phases 1 and 3 at the braking point, brakes to stop on the marks (service brakes, or in
    TC braking the engine speed at which the converter brakes as needed, eased into 1.2 s before the
    braking point) and stops the bucket at the dump height; the driver's request sets the engine speed
    everywhere else.

    WheelLoaderTarget-v3 (``assist=True, coast=True``): ``Box(-1, 1, (4,), float32)``, v2's three and

    | Num | Action                                   | -1                    | +1                  |
    |-----|------------------------------------------|-----------------------|---------------------|
    | 3   | coasting deceleration, of the limit: the leg (phase 3; phase 1 with service braking) ends at its braking point, where coasting in neutral carries the machine past the mark | 15 % | 95 % |

    The service brakes then act only from the braking point at the braking fraction on: the machine coasts
    in neutral until then, as the fuel-optimal cycles do (they shift at 20-30 % of the deceleration the
    stop would need and brake late and hard). A coasting fraction at or above the braking fraction ends the
    leg at the braking point, as in v2.

    WheelLoaderTarget-v4 (``assist=True, coast=True, guards=True``): v3's actions, and three guards in the assist
    (:mod:`wl_env.assist`, "The guards") for what a driver can get wrong at the edges of the scenario ranges:
    a machine crawling or standing short of its mark in phase 1 or 3 gets at least the engine speed that moves
    it off (and a leg standing on its mark ends); in phase 4 a lift that would outlast the stop goes on at full
    acceleration; with TC braking the lift is timed so the shift into forward gear keeps the deceleration
    limit (a lift that would end early is held for the braking, an idle bucket lifts while the engine is above
    its metered speed, the lift-off aims at 88 % of the limit instead of 95 %).

    WheelLoaderTarget-v5 (``lift_floor=True`` as well): v4, and a lifting bucket keeps the engine-speed request at
    least 1.3 omega_min (``wl_env.assist.LIFT_ENGINE_FLOOR``; the TC metering aside): the lift's load rises within
    a step faster than the governor meters, and stalled idling engines under the lift.

    WheelLoaderTarget-v6 (``lift_off_load=True`` as well): v5, and with TC braking the guards' lift loads an engine
    above its metered speed at full acceleration through the lift-off and the braking whatever the bucket's
    speed (v4 and v5: only a bucket slower than 0.1 m/s). The same as v5 with service braking.

    WheelLoaderTarget-v7 (``step_braking=True`` as well): v6, and the braking ends on the 0.1 s step grid as the
    minimum-time optimum's does: its first step takes up what a leg ended at a step boundary leaves over, and
    the steps after it brake at the driver's fraction (v2-v6 brake at the constant deceleration that stops on
    the mark, below the fraction by up to a step's travel). The actions are v6's.

    WheelLoaderTarget-v1 (``fuel_action="engine_speed"``): action 0 is an engine-speed request to the
    engine's governor, -1 at omega_min + 5 rad/s, +1 at omega_max. The governor injects what takes the
    engine to the request within the interval under the load at its start (the model inverted in U_mf,
    :func:`wl_env.model.governed_injection`); the machine clips it as any injection. Fuel is then a
    monotone function of the requested speed, where an injection command above what a neutral engine
    needs is capped at omega_max and shows a learner no gain from less.
    The machine saturates what it cannot do (torque limit, governor at omega_max, relief pressure, pump
    flow, no lowering of the bucket); ``info["saturations"]`` says which were active.

    ## Observation Space

    ``Box((21,), float32)`` in WheelLoaderTarget-v0, ``Box((19,), float32)`` in v2, ``Box((12,), float32)`` in v1, normalized (:class:`wl_env.codec.Codec`
    encodes and decodes it by name):

    | Num  | Observation (v2; v1 where it differs)                   | Min  | Max |
    |------|---------------------------------------------------------|------|-----|
    | 0    | engine speed omega / omega_max                          | 0    | 1.5 |
    | 1    | vehicle speed V / V_max (fwd > 0)                       | -1.5 | 1.5 |
    | 2    | bucket height H / 5 m (v1: H / H_T)                     | 0    | 1.5 |
    | 3    | bucket speed V_b (m/s)                                  | 0    | 2   |
    | 4    | position s / 6.6 m (v1: / reverse_distance; start = 0)  | -2.5 | 1.5 |
    | 5    | distance to the leg's end / 6.6 m (v1: as 4)            | -1.5 | 2.5 |
    | 6    | elapsed time / 40 s                                     | 0    | 1.5 |
    | 7    | fuel used (kg)                                          | 0    | 5   |
    | 8-11 | phase one-hot (1, 2, 3, 4)                              | 0    | 1   |
    | 12-18| v2 only: the scenario's payload, reverse and forward distance, rolling resistance, dump height, start engine speed and start bucket height, each mapped from its range onto [-1, 1] | -1 | 1 |
    | 19   | target only: the episode's target cycle time / 40 s                   | 0    | 1   |
    | 20   | target only: target / T_min - 1 (T_min: the scenario's estimate, :mod:`wl_env.suites.min_time`) | -1 | 6 |

    ## Rewards

    Each step: ``-(w_fuel * fuel_g / fuel_ref_g + w_time * dt / time_ref)``, minus ``violation`` times
    the time-integrated relative excess over the limits of eq. (31) (deceleration 0.18 g and speed V_max
    at every RK4 stage and substep end; torque curve, pump flow and relief pressure at each substep's end
    under the held control; :mod:`wl_env.limits`, reported per limit in ``info["violations"]``),
    plus a potential-based progress term (``shaping``). Once: minus ``target_distance`` per metre of
    error at the reversing point (s = -reverse_distance) and at the truck (s = forward_distance -
    reverse_distance), minus ``target_height`` per metre of
    bucket-height error at the end, minus ``failure`` for a stall or leaving the site. See
    :class:`wl_env.episode.RewardConfig`; ``w_fuel``/``w_time`` trace the fuel-time trade-off.
    WheelLoaderTarget-v0 (``observe_target``) has ``w_time`` 0 and charges ``late`` per unit of (t - T) / T past the
    episode's target T as it accrues: a target between T_min and ~2.5 T_min traces the front. The target
    is ``target`` (a ratio to T_min, or a range drawn from at each reset, uniformly unless ``target_power``
    is not 1: lo + (hi - lo) u**target_power; default 1-2.5) times
    the scenario's estimated T_min, or ``reset(options={"target_time": T})`` / ``{"target_ratio": r}``;
    ``info["target_time"]``, and ``info["lateness"]`` ((t - T) / T when positive, else 0).

    ## Starting State

    The scenario's start: omega = 1500 rpm, H = 0.7 m in the paper's cycle (Table II); V = 0, V_b = 0, s = 0,
    phase 1. ``init_noise`` > 0 adds a seeded uniform perturbation of omega (+-init_noise * 100 rpm) and H
    (+-init_noise * 0.1 m).

    ## Episode End

    | Outcome    | Condition                                                                 |
    |------------|---------------------------------------------------------------------------|
    | terminated | cycle completed: phase 4, V = 0 and the bucket still (``info["is_success"]`` if the reversing point, the end position (5 cm) and the height (2 cm) are met) |
    | terminated | failure: engine stall (omega < omega_min) or off the site (more than a reverse distance behind the reversing point or past the truck) |
    | truncated  | elapsed time >= ``max_time`` (default 40 s)                                |

    ``step()`` after the episode has ended raises ``RuntimeError``: call ``reset()``.

    ## Version History

    * WheelLoaderTarget-v7: v6 with the braking on the step grid (``step_braking``). An all-out driver that reads
      the plant (``scripts/bench_assist_floor.py``, 20 `test` cycles at T_min) ended 2.09 % over T_min (median)
      against v6's 2.73 % with service braking, 7.34 % against 7.94 % with TC braking.
    * WheelLoaderTarget-v6: v5 with the lift-off's full load (``lift_off_load``). On 200 fresh `train` draws at
      T_min a TC driver trained on v5 met the shift into forward gear with its engine high and broke the
      deceleration limit at 5 (by up to 20 %).
    * WheelLoaderTarget-v5: v4 with the lift's engine floor (``lift_floor``). At the 128 corners of the scenario
      ranges v4's shipped service drivers stalled the engine under the last lift at 5 (1.5 T_min).
    * WheelLoaderTarget-v4: v3 with the assist's guards (``guards``): the creep floor, the last lift and, with TC
      braking, the lift timing. At the 128 corners of the scenario ranges v3's shipped TC drivers broke the
      deceleration limit at 7-22 (by up to 72 %), and its service drivers stood short of the truck at up to 6.
    * WheelLoaderTarget-v3: v2 with a fourth driver action, the coasting fraction at whose braking point the
      leg ends early to coast in neutral (``coast``); the service brakes act from the braking point.
    * WheelLoaderTarget-v2: v1 driven through the stopping assist (``assist``): three driver actions.
    * WheelLoaderTarget-v1: v0 with action 0 the governor's engine-speed request (``fuel_action``).
    * WheelLoaderTarget-v0 (a task of its own): v2 with a target cycle time per episode
      (``observe_target``): two more observation entries, the lateness term, no time term (``w_time`` 0).
    * v2: scenarios (``scenario=``, ``reset(options={"scenario": ...})``, ``info["scenario"]``), the
      scenario's features in the observation, fixed length scales (5 m, 6.6 m); the two legs' distances
      may differ. The paper's cycle runs the same numbers as in v1.
    * v1: every limit checked within the step (at the RK4 stages and the substep's end, where the
      benchmark checks it), elapsed time observed as t / 40 s (not t / max_time), a stalled engine stops
      at omega = 0, ``step()`` after the end raises.
    * v0: the limits at substep starts only (a controller could exceed 0.18 g unseen between two).
    """

    metadata = {"render_modes": ["rgb_array", "human"], "render_fps": 10}

    def __init__(
        self,
        braking: str | None = None,
        params: LoaderParams | dict | None = None,
        dt: float = 0.1,
        substeps: int = 1,
        max_time: float = 40.0,
        reward: RewardConfig | dict | None = None,
        w_fuel: float | None = None,
        w_time: float | None = None,
        init_noise: float = 0.0,
        render_mode: str | None = None,
        scenario: Scenario | dict | str | None = None,
        observe_scenario: bool = True,
        observe_target: bool = False,
        target: float | tuple[float, float] = TARGET_RATIOS,
        target_power: float = 1.0,  # the draw's exponent in the range (check_target_power): 1 uniform
        fuel_action: str = "injection",  # or "engine_speed": action 0 is the governor's request
        assist: bool = False,  # WheelLoaderTarget-v2: the driver's 3 actions through the stopping assist
        coast: bool = False,  # WheelLoaderTarget-v3: the assist's coasting variant (a 4th action: the coasting fraction)
        guards: bool = False,  # WheelLoaderTarget-v4: the assist's guards (creep floor, last lift, TC lift timing)
        lift_floor: bool = False,  # WheelLoaderTarget-v5: the engine-speed floor under a lifting bucket
        lift_off_load: bool = False,  # WheelLoaderTarget-v6: the TC lift-off loads the engine with a full lift
        step_braking: bool = False,  # WheelLoaderTarget-v7: the braking's first step takes up the step grid's rest
    ) -> None:
        self.assist = check_assist(assist, fuel_action, coast, guards, lift_floor, lift_off_load, step_braking)
        self.coast, self.guards, self.lift_floor, self.lift_off_load = coast, guards, lift_floor, lift_off_load
        self.step_braking = step_braking
        self.machine = resolve_machine(params)  # the machine; a scenario sets its cycle's fields
        self.observe_target = check_flag("observe_target", observe_target)
        if self.observe_target and not check_flag("observe_scenario", observe_scenario):
            raise ValueError("observe_target needs observe_scenario (the target's observation extends v2's)")
        self.target_ratios = check_target_ratios(target)
        self.target_power = check_target_power(target_power)
        self._source, self.braking = scenario_source(scenario, braking, self.machine)
        check_no_overridden(params, self._source)
        self._params_given = params  # (a reset's scenario is checked against it too)
        check_target_cycle(self.observe_target, self._source, self.machine, self.braking)
        init_noise = plain(init_noise)
        if isinstance(init_noise, bool) or not (isinstance(init_noise, (int, float)) and 0.0 <= init_noise <= 1.0):
            raise ValueError(f"init_noise must lie in [0, 1], got {shown(init_noise)}")
        if render_mode is not None and not (isinstance(render_mode, str) and render_mode in self.metadata["render_modes"]):
            raise ValueError(f"render_mode must be one of {self.metadata['render_modes']} or None, got {shown(render_mode)}")
        self.render_mode = render_mode
        self.init_noise = float(init_noise)
        self.observe_scenario = check_flag("observe_scenario", observe_scenario)
        fixed = self._source if isinstance(self._source, Scenario) else None
        self.params = fixed.params(self.machine) if fixed is not None else self.machine
        self.scenario = fixed or start_scenario(self.machine, self.braking, self.machine.omega_0, self.machine.H_0)
        self.core = CycleStepper(self.params, self.braking, dt, substeps, max_time,
                                 make_reward_config(reward, w_fuel, w_time), self.observe_scenario,
                                 fuel_action)
        self.action_space = spaces.Box(-1.0, 1.0, (n_actions(self.assist, self.coast),), np.float32)
        codec = self.core.codec
        low, high = (TARGET_OBS_LOW, TARGET_OBS_HIGH) if self.observe_target else (codec.obs_low, codec.obs_high)
        self.observation_space = spaces.Box(low, high, dtype=np.float32)
        self.codec = codec
        self.target_time = math.nan  # s, the episode's (observe_target)
        self.min_time_estimate = math.nan
        self._gears = self.core.sim._tables_py[0]
        self._done = False
        self._renderer = None
        self._y: tuple = ()
        self._phase = 1
        self._t = 0.0
        self._rev_err = math.nan
        self._violation = 0.0

    # ------------------------------------------------------------------ gym API
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        seed = plain(seed)  # (a numpy integer; gymnasium's own refusal is not a ValueError and takes True for 1)
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int) or seed < 0):
            raise ValueError(f"seed must be an integer >= 0 or None, got {shown(seed)}")
        self._done = True  # (until this reset succeeds: one that fails leaves no half-reset episode to step)
        if options is not None and not isinstance(options, dict):
            raise ValueError(f"WheelLoaderEnv.reset's options must be a dict or None, got {shown(options)}")
        options = dict(options or {})
        chosen = options.pop("scenario", None)
        target_time, target_ratio = options.pop("target_time", None), options.pop("target_ratio", None)
        if options:
            allowed = "the options 'scenario', 'target_time' and 'target_ratio'" if self.observe_target else (
                "only the option 'scenario'")
            raise ValueError(f"WheelLoaderEnv.reset takes {allowed}, got {sorted(map(str, options))}")
        if not self.observe_target and (target_time is not None or target_ratio is not None):
            raise ValueError("a target cycle time is an option of WheelLoaderTarget-v0 (observe_target=True)")
        # Every option is checked before the generator is seeded or drawn from: a refused reset (a target of 50 s)
        # reseeded it and drew a scenario, so the episodes after it were not the seed's.
        if target_time is not None and target_ratio is not None:
            raise ValueError("give the option target_time or target_ratio, not both")
        if target_time is not None:
            check_target_time(target_time)
        if target_ratio is not None:
            check_target_ratios(target_ratio, "target_ratio")
        source = self._source if chosen is None else scenario_source(chosen, self.braking, self.machine)[0]
        if chosen is not None:  # (the payload params= set was replaced by the scenario's without a word)
            check_no_overridden(self._params_given, source)
        super().reset(seed=seed)
        if isinstance(source, Suite):
            source = source.sample(self.np_random, self.braking)
        self._set_scenario(source)
        p = self.params
        omega, H = p.omega_0, p.H_0
        if self.init_noise > 0.0:
            du = self.np_random.uniform(-1.0, 1.0, size=2)
            omega += float(du[0]) * self.init_noise * 100.0 * math.pi / 30.0
            H += float(du[1]) * self.init_noise * 0.1
        self._y = (float(omega), 0.0, float(H), 0.0, 0.0, 0.0)
        self._phase, self._t, self._rev_err, self._violation = 1, 0.0, math.nan, 0.0
        self._features = self.codec.encode_observation(self._y, self._phase, self._t)
        # The cycle this episode runs, its actual start included: what it is scored against.
        self.episode_params = p.replace(omega_0=float(omega), H_0=float(H)) if self.init_noise > 0.0 else p
        self.episode_scenario = start_scenario(p, self.braking, omega, H) if self.init_noise > 0.0 else self.scenario
        if self.observe_target:
            self.min_time_estimate, self.target_time = episode_target(
                self.episode_scenario or self.scenario, self.target_ratios, self.np_random, target_time, target_ratio,
                self.target_power)
        self._done = False
        if self.render_mode == "human":
            self.render()
        info = {"t": 0.0, "phase": 1, "fuel_g": 0.0, "scenario": self.episode_scenario}
        if self.observe_target:
            info["target_time"] = self.target_time
        return self._obs(), info

    def _set_scenario(self, scenario: Scenario | None) -> None:
        """Drive ``scenario``'s cycle (None: the machine's own parameters) from now on."""
        if scenario is not None and scenario.braking != self.braking:
            raise ValueError(f"this env runs {self.braking} braking; the scenario has {scenario.braking!r}")
        params = self.machine if scenario is None else scenario.params(self.machine)
        p = self.machine
        self.scenario = scenario or start_scenario(p, self.braking, p.omega_0, p.H_0)
        if params != self.params:
            c = self.core
            self.params = params
            self.core = CycleStepper(params, self.braking, c.dt, c.substeps, c.max_time, c.reward, self.observe_scenario,
                                     c.fuel_action)
            self.codec = self.core.codec

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        if not self._y:
            raise RuntimeError("call reset() before step()")
        if self._done:
            raise RuntimeError("the episode has ended (terminated or truncated) or its reset failed: call reset() before step()")
        a = action_array(action, "action")
        if a.shape != self.action_space.shape:
            names = ("[engine-speed request, bucket, braking fraction, coasting fraction]" if self.coast else
                     "[engine-speed request, bucket, braking fraction]" if self.assist else "[fuel, bucket, brake, shift]")
            raise ValueError(f"action must have shape {self.action_space.shape} {names}, got shape {a.shape}")
        values = a.tolist()  # checked as Python floats (numpy calls would cost more); the step clips them
        if not all(map(math.isfinite, values)):
            raise ValueError(f"action must be finite numbers in [-1, 1], got {values}")
        return self._advance(values)

    def _advance(self, values: list[float]) -> tuple[np.ndarray, float, bool, bool, dict]:
        """One step under the checked action ``values`` (this env's layout; the plan env's driver acts here)."""
        if self.assist:
            y, phase = self._y, self._phase
            values = [float(v) for v in assisted_action(y, phase, self.codec.distance_to_go(y[4], phase), values,
                                                        self.params, self.braking, self.core.dt, self.coast,
                                                        self.guards, self.lift_floor, self.lift_off_load,
                                                        self.step_braking)]
        t0, core = self._t, self.core
        r = core.step(self._y, self._phase, self._t, self._rev_err, self._violation, values)
        y = r["y"]
        # (core.diverged inline: NaN fails the comparisons too)
        if not (y[0] <= core.omega_diverged and -core.speed_diverged <= y[1] <= core.speed_diverged):
            self._done = True  # (no episode to step on)
            raise core.divergence(y, t0)
        self._y, self._phase, self._t = y, int(r["phase"]), r["t"]
        if self.observe_target:
            r["reward"] = r["reward"] - lateness_charge(t0, r["t"], self.target_time, self.core.reward.late)
        self._rev_err, self._violation = r["rev_err"], r["violation"]
        self._features = r["obs"]
        terminated, truncated = bool(r["terminated"]), bool(r["truncated"])
        self._done = terminated or truncated
        if self.render_mode == "human":
            self.render()
        return self._obs(), float(r["reward"]), terminated, truncated, self._info(r)

    def _obs(self) -> np.ndarray:
        if self.observe_target:
            return np.array([*self._features, *target_features(self.target_time, self.min_time_estimate)], dtype=np.float32)
        return np.array(self._features, dtype=np.float32)  # (the step computed and clipped them, flattened)

    def _info(self, r: dict) -> dict[str, Any]:
        y = self._y
        return {
            "t": self._t,
            "fuel_g": y[5] * 1000.0,
            "phase": self._phase,
            "gear": r["gear"],
            "tc_mode": r["tc_mode"],
            "phi": r["phi"],
            "state": y[:4],
            "s": y[4],
            "controls": r["u"],
            "saturations": r["saturations"],
            # per limit (wl_env.limits.ENV_NAMES), its largest relative excess within this step; "excess" the
            # largest of them, "max_excess" the largest so far in the episode
            "violations": {"deceleration": r["excess_deceleration"], "speed": r["excess_speed"],
                           "excess": r["excess"], "max_excess": self._violation},
            "reversing_error": None if math.isnan(self._rev_err) else self._rev_err,  # m, None until reached
            "is_success": bool(r["success"]),
            "completed": bool(r["completed"]),
            "stalled": bool(r["stalled"]),
            "off_site": bool(r["off_site"]),
            "scenario": self.episode_scenario,
            **({"target_time": self.target_time, "lateness": max(self._t - self.target_time, 0.0) / self.target_time}
               if self.observe_target else {}),
        }

    # ------------------------------------------------------------------ extras
    @property
    def state(self) -> np.ndarray:
        """The model state [omega (rad/s), V (m/s), H (m), V_b (m/s)]."""
        return np.array(self._y[:4])

    @property
    def phase(self) -> int:
        return self._phase

    @property
    def position(self) -> float:
        """Travelled position s (m, forward > 0)."""
        return self._y[4]

    @property
    def fuel_g(self) -> float:
        return self._y[5] * 1000.0

    @property
    def time(self) -> float:
        return self._t

    def render(self) -> np.ndarray | None:
        from wl_env.rendering import render_frame

        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; pass render_mode='rgb_array' or 'human'")
            return None
        frame = render_frame(self)
        if self.render_mode == "human":
            from wl_env.rendering import show

            self._renderer = show(frame, self._renderer)
            return None
        return frame

    def close(self) -> None:
        if self._renderer is not None:
            import matplotlib.pyplot as plt

            plt.close(self._renderer[0])
            self._renderer = None
