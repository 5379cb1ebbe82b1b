"""The driving assist of ``WheelLoaderTarget-v2`` to ``-v7``: an operator's stopping laws under a learned driver.

A driver (a policy) picks how to drive; the assist stops the machine on the marks. The assist's laws are
the rule-based operator's (:mod:`agents.operator` calls the same functions):

* **braking point**: in phases 1 and 3 the assist shifts (ends the leg) at the step after which braking
  at the chosen fraction of the deceleration limit would stop the machine past its mark;
* **braking**: in phases 2 and 4 it asks the deceleration that stops the machine on the mark (at most
  98 % of the limit): the service brakes' torque where they act, else (TC braking, phase 2) the engine
  speed at which the converter in forward gear brakes with it (the model, bisected in omega; at most
  ``TC_MAX_FRACTION`` of the limit, a margin for its rise within the step);
* **TC lift-off**: with TC braking the engine is brought to that speed ``TC_LIFT_OFF_TIME`` before the
  braking point, since the converter would brake far too hard from a racing engine. From an engine far
  above that speed 1.2 s is not enough (an unfuelled engine comes down at ~20-40 rad/s^2): the driver's
  request must come down in time (a learned driver does; an earlier lift-off computed from the unfuelled
  engine's descent cost a trained driver 11-16 points of fuel gap, docs/benchmarks.md section 7). The pump's
  load helps it down: a driver that holds the bucket still through the lift-off meets the braking point with
  the engine at ~135 rad/s, and the converter brakes up to 162 % over the limit (measured, stop 36);
* **bucket**: never faster than the speed from which 80 % of the strongest bucket deceleration stops it
  at the dump height, so it stops there whatever the driver asks.

What the driver sets (each in [-1, 1]): the engine-speed request (as action 0 of WheelLoaderTarget-v1,
through the governor, wherever the assist does not meter the converter), the bucket acceleration it asks
(as action 1; the stopping curve caps it) and the braking deceleration as a fraction of the limit
(-1: 50 %, +1: 95 %), which sets where the leg ends.

**Coasting** (``coast``, WheelLoaderTarget-v3). The MPC's lean cycles shift to neutral early (where braking
would need 20-30 % of the limit), roll, and brake late and hard (87-97 % of the limit): at the same fuel,
a faster stop than v2's constant deceleration from its braking point, which cannot express them. v3's
driver has a fourth action, the coasting fraction: the leg ends at the braking point of that fraction
(:func:`early_shift`: in the legs the service brakes end, where coasting carries the machine past the mark),
and the service brakes act only from the braking point at the braking fraction on. A coasting fraction at
or above the braking fraction makes v3 drive v2's cycle.

**The guards** (``guards``, WheelLoaderTarget-v4). Three things v3 left to the driver that a driver can get wrong
at the edges of the scenario ranges.

*The creep floor* (both brakings): in phases 1 and 3 a machine slower than ``CREEP_SPEED`` short of its mark
(by more than the marks' 5 cm) gets at least the engine speed at which it moves off at ``CREEP_ACCELERATION``
(:func:`creep_speed`), and a leg standing on its mark ends (the braking point only ends a moving one). v3's
shipped service drivers, asking for an idling engine at 1.5 T_min, let 13 t machines at c_r 0.05 roll to a
stop 14-24 cm short of the truck, or stand on the mark without ending the leg, until the 40 s limit (6 of the
128 corners).

*The last lift* (both brakings): in phase 4, where the lift left to the dump height (at the pump's speed now)
would outlast the stop, the bucket lifts at full acceleration (the stopping curve still stops it at the dump
height; the cycle ends once it is still). Drivers that stopped lifting early ended 3-277 cm short at 7 of the
128 TC corners (v4's first fine-tuned policies) and 31 cm at one service corner.

*The TC lift guard* (TC braking). v3's TC lift-off left the
shift's braking to the engine speed the driver had brought: at the corners of the scenario ranges the shipped
v3 drivers met the shift with the engine at 88-120 rad/s and the converter braked up to 72 % over the limit
(measured, stop 38). The pump's load is the only thing that brings an unfuelled engine below the speed the
wheels hold it at, so v4's assist times the lift as the rule-based operator does:

* it holds the bucket in phase 1, before the lift-off, while the lift left would end before the machine stops
  from the braking point (:func:`lift_done_early`): the lift then runs into the braking;
* through the lift-off and the braking it lifts a bucket the driver leaves idle while the engine is above
  the speed the converter is metered at;
* the lift-off aims at ``TC_LIFT_OFF_FRACTION`` of the limit, a margin for an engine that has not come all the
  way down at the shift.

*The lift's engine floor* (``lift_floor``, WheelLoaderTarget-v5). A lifting bucket keeps the engine-speed request at
least ``LIFT_ENGINE_FLOOR`` times omega_min (outside the TC metering, whose speed is above it). The governor meters
the injection from the load at the step's start; a lift that speeds up within the step (the last lift's full
acceleration, or the driver's) loads an idling engine faster than that. The v4 service drivers at 1.5 T_min stalled
13 t machines at c_r 0.05 in phase 4 (5 of 128 corners, 50-57 rad/s at the end), and a driver idling the engine
while lifting at full acceleration stalled it at 72 of the 128 TC corners and 14 service ones (measured, stop 40). The
floor changes a cycle only where the engine would run below it under the lift: 22 of the v4 bc service driver's
128 corner cycles at 1.5 T_min (-0.40..+0.54 % fuel, its 2 stalls gone), 3 of the v4 ppo service driver's 50
`test` cycles (within 0.02 %).

*The lift-off's full load* (``lift_off_load``, WheelLoaderTarget-v6; TC braking). v4's TC lift guard lifts only a
bucket slower than ``IDLE_BUCKET_SPEED``: a driver that slows a lifting bucket through the lift-off (asking a
negative bucket acceleration after the guard's kick) keeps the pump's load, and so the engine's descent, small.
A TC driver trained from scratch on v5 met the shift at 86-94 rad/s (the metering asked 78) at 1.3-1.5 m/s, and
the converter braked 3-20 % over the limit on 5 of 200 fresh `train` draws at T_min (measured, stop 42). v6 lifts
at full acceleration (the stopping curve still caps it) whenever the engine is above its metered speed in the
lift-off and the braking: those 5 cycles then kept the limit, at -0.9..+0.3 g of fuel.

*The braking on the step grid* (``step_braking``, WheelLoaderTarget-v7). A leg ends at a step boundary, the step
before braking at the driver's fraction would carry the machine too far, so v2-v6's constant deceleration that
stops on the mark from there runs below that fraction, by up to a step's travel (~14 % of the braking distance at
2.5 m/s), and the stop comes later. The minimum-time optimum brakes whole steps at the limit. v7's braking
(:func:`step_braking_deceleration`) asks in each step the deceleration after which braking at the driver's
fraction stops on the mark: the first braking step takes up what the step grid leaves over, the rest run at the
fraction. An all-out driver that reads the plant ended 2.09 % over T_min (median of 20 `test` cycles, service
braking) against v6's 2.73 %: 9 of the 20 cycles a step shorter, none longer; CMA-ES searches of the plan family at
T_min found plans 11.5-21.7 % over the optimum's fuel (v6: 20.7-24.0 %) at 1.3-2.3 % lateness (measured, stop 62).

Written for floats and numpy arrays of loaders (the vector env's :class:`~wl_env.params.ParamsView`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from wl_env import cycle
from wl_env.codec import encode_speed_request
from wl_env.episode import DISTANCE_TOL, HEIGHT_TOL
from wl_env.model import derivatives
from wl_env.params import LoaderParams
from wl_env.physics import lift

N_ASSIST_ACTIONS = 3  # engine-speed request, bucket acceleration, braking fraction of the deceleration limit
N_COAST_ACTIONS = 4  # WheelLoaderTarget-v3: and the coasting fraction (where the leg ends to coast)
# of the deceleration limit, the range of v3's fourth action: the leg ends to coast at the braking point of this
# fraction (the MPC's lean cycles shift at 20-30 %; coasting alone slows the machine by ~14 % of the limit)
COAST_FRACTION = (0.15, 0.95)
BRAKING_FRACTION = (0.5, 0.95)  # of the deceleration limit, the range of the driver's third action
MAX_BRAKING_FRACTION = 0.98  # the braking itself asks at most this fraction of the limit
# The converter's braking rises within a step as the machine slows (its speed ratio falls): metered from the
# step's start, it aims at most this fraction (0.98 overshot the limit by 0.75 % within a step).
TC_MAX_FRACTION = 0.95
TC_LIFT_OFF_TIME = 1.2  # s before the braking point a TC-braking driver brings the engine down
# WheelLoaderTarget-v4's lift-off aims lower than the braking's metering (TC_MAX_FRACTION): at 0.95 an engine a
# few rad/s above its aim at the shift put 20 of 128 corners 0.1-1.7 % over the limit (measured, stop 39)
TC_LIFT_OFF_FRACTION = 0.88
IDLE_BUCKET_SPEED = 0.1  # m/s: below it v4's guard takes a bucket for idle (and lifts it to load the engine)
# m/s^2 with which v4's creep floor moves a machine standing short of its mark (the driver's request may be
# lower: a 13 t machine at c_r 0.05 stood 20 cm short on an idling engine until the 40 s limit; measured, stop 39)
CREEP_ACCELERATION = 0.3
CREEP_SPEED = 0.3  # m/s: below it, short of the mark, the creep floor holds (a floor at standstill only crawled)
LIFT_TIMING_SPEED = 1.0  # m/s: the least speed the lift is timed with (the machine starts from rest)
BUCKET_STOP_FRACTION = 0.8  # of the strongest bucket deceleration, the stopping curve's
MIN_MOVING_SPEED = 0.05  # m/s: below it a leg is not ended by the braking point (the machine is starting)
TC_SPEED_FLOOR = 1.3  # the converter's braking speed stays above this times omega_min (clear of a stall)
# times omega_min: v5's least engine-speed request while the bucket lifts (in phase 4 alone, 1.15 left 1 of the 2
# stalls of the v4 bc driver's 128 service corners at 1.5 T_min; 1.3 none; measured, stop 40)
LIFT_ENGINE_FLOOR = 1.3
_BISECTIONS = 20


def stopping_distance(speed: Any, deceleration: Any) -> Any:
    """m to stand still from ``speed`` (m/s) at ``deceleration`` (m/s^2)."""
    return speed * speed / (2.0 * deceleration)


def braking_point(phase: Any, speed: Any, distance_to_go: Any, deceleration: Any, dt: float) -> Any:
    """Whether to end the leg now (phases 1 and 3): braking from the next step on at ``deceleration``
    would stop past the mark."""
    return (((phase == 1) | (phase == 3)) & (speed > MIN_MOVING_SPEED)
            & (stopping_distance(speed, deceleration) >= distance_to_go - speed * dt))


def fraction_action(speed: Any, distance_to_go: Any, p: LoaderParams, dt: float,
                    bounds: tuple[float, float] = BRAKING_FRACTION) -> Any:
    """The driver's fraction action (in [-1, 1], clipped; ``bounds`` the fractions of the deceleration limit
    at -1 and +1: the braking fraction's, or :data:`COAST_FRACTION`) with which :func:`braking_point` ends the
    leg at this state: braking from the next step on at that deceleration stops on the mark. The inverse of
    the law in :func:`assisted_action`, for labelling an expert's shift or braking as a driver action."""
    a = speed * speed / (2.0 * np.maximum(distance_to_go - speed * dt, 1e-3))
    lo_f, hi_f = bounds
    return np.clip(2.0 * (a / (p.decel_max * p.g) - lo_f) / (hi_f - lo_f) - 1.0, -1.0, 1.0)


def stopping_deceleration(speed: Any, distance_to_go: Any, p: LoaderParams) -> Any:
    """m/s^2 that stops the machine on the mark, at most ``MAX_BRAKING_FRACTION`` of the limit (0 standing)."""
    a_limit = p.decel_max * p.g
    a = np.minimum(speed * speed / (2.0 * np.maximum(distance_to_go, 1e-3)), MAX_BRAKING_FRACTION * a_limit)
    return np.where(speed > 1e-3, a, 0.0)


def step_braking_deceleration(speed: Any, distance_to_go: Any, deceleration: Any, p: LoaderParams, dt: float) -> Any:
    """m/s^2 for the coming step after which braking at ``deceleration`` stops the machine on the mark: the
    braking's first step takes up what a leg ended on the step grid leaves over, and the rest runs at the
    planned deceleration (the minimum-time optimum's whole steps at the limit). A machine that stops within this
    step asks what stops it on the mark. At most ``MAX_BRAKING_FRACTION`` of the limit, 0 standing."""
    a_limit = p.decel_max * p.g
    d = np.maximum(distance_to_go, 1e-3)
    disc = deceleration * (deceleration * dt * dt - 4.0 * speed * dt + 8.0 * d)
    first = speed + 0.5 * deceleration * dt - 0.5 * np.sqrt(np.maximum(disc, 0.0))  # m/s shed in the step
    within = (disc < 0.0) | (first >= speed)  # the stop falls inside the step
    a = np.where(within, speed * speed / (2.0 * d), first / dt)
    a = np.clip(a, 0.0, MAX_BRAKING_FRACTION * a_limit)
    return np.where(speed > 1e-3, a, 0.0)


def stopping_time(speed: Any, distance_to_go: Any, planned: Any) -> Any:
    """s until the machine stands on the mark under v7's braking, for its last lift: at ``planned`` (m/s^2) from its
    braking point on, or at the deceleration that stops on the mark where that point is passed. (v2-v6's clock,
    speed over their constant deceleration, counts up to twice the time left under v7's braking: buckets stopped
    short of the dump height, 4 of 2048 random plans.)"""
    v = np.maximum(speed, 1e-3)
    d = np.maximum(distance_to_go, 0.0)
    return np.where(d >= stopping_distance(v, planned), d / v + v / (2.0 * planned), 2.0 * d / v)


def brake_torque(deceleration: Any, p: LoaderParams) -> Any:
    """N m of service brake that decelerates the machine by ``deceleration`` (rolling resistance helps)."""
    return np.clip((p.M_tot * deceleration - p.F_roll) * p.r_w, 0.0, p.U_b_max)


def tc_braking_speed(V: Any, H: Any, V_b: Any, deceleration: Any, p: LoaderParams, braking: str = "tc") -> Any:
    """rad/s: the engine speed at which the converter in forward gear decelerates the reversing machine by
    ``deceleration`` (it brakes harder the faster the engine turns: bisected), within
    [TC_SPEED_FLOOR omega_min, omega_max]."""
    spec = cycle.phase_specs(braking, p)[1]

    def decel(omega: Any) -> Any:
        return derivatives(omega, V, H, V_b, 0.0, 0.0, 0.0, spec.gear, spec.direction, p)[1]

    return _speed_for(decel, deceleration, p.omega_min * TC_SPEED_FLOOR + 0.0 * V, p.omega_max + 0.0 * V)


def creep_speed(p: LoaderParams, braking: str) -> Any:
    """rad/s: the engine speed at which the machine, standing in gear, moves off at ``CREEP_ACCELERATION`` (at
    most omega_max). The converter at stall against the rolling resistance: the same in phases 1 and 3 and
    whatever the bucket does, so it is a property of the machine, computed once per machine (the vector env
    asked for it on nearly every step: a third of its throughput, measured)."""
    values = getattr(p, "values", None)  # a ParamsView: one machine per loader
    key = (braking, p) if values is None else (braking, p.base, *(np.asarray(values[f]).tobytes() for f in ("M_load", "c_r")))
    speed = _CREEP_SPEEDS.get(key)
    if speed is None:
        spec = cycle.phase_specs(braking, p)[2]
        standing = 0.0 * np.asarray(p.M_load)

        def acceleration(omega: Any) -> Any:
            return derivatives(omega, standing, standing, standing, 0.0, 0.0, 0.0, spec.gear, spec.direction, p)[1]

        speed = _speed_for(acceleration, CREEP_ACCELERATION, p.omega_min + standing, p.omega_max + standing)
        if len(_CREEP_SPEEDS) >= 256:  # (the vector env draws a new set of machines at every autoreset)
            _CREEP_SPEEDS.clear()
        _CREEP_SPEEDS[key] = speed
    return speed


_CREEP_SPEEDS: dict[tuple, Any] = {}


def _speed_for(rate: Any, target: Any, lo0: Any, hi0: Any) -> Any:
    """The engine speed in [lo0, hi0] at which ``rate`` (rising with the engine speed, as the converter's
    torque does) reaches ``target``: bisected; lo0 where it is already reached there, hi0 where never."""
    lo, hi = lo0, hi0
    for _ in range(_BISECTIONS):
        mid = 0.5 * (lo + hi)
        below = rate(mid) < target
        lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
    inner = 0.5 * (lo + hi)
    return np.where(rate(lo0) >= target, lo0, np.where(rate(hi0) <= target, hi0, inner))


def bucket_command(H: Any, V_b: Any, asked: Any, p: LoaderParams, dt: float) -> Any:
    """m/s^2: the bucket acceleration ``asked``, capped by the curve on which ``BUCKET_STOP_FRACTION`` of
    the strongest bucket deceleration stops the bucket at the dump height (the height left counted from
    the end of the coming step, which the command holds for)."""
    ab_lo, ab_hi = p.U_ab_bounds
    h_left = np.maximum(p.H_T - H - V_b * dt, 0.0)
    v_stop = np.sqrt(2.0 * BUCKET_STOP_FRACTION * -ab_lo * h_left)
    return np.clip((v_stop - V_b) / dt, ab_lo, np.minimum(asked, ab_hi))


def lift_done_early(omega: Any, speed: Any, H: Any, distance_to_go: Any, deceleration: Any, p: LoaderParams) -> Any:
    """Whether the lift left, at the pump's speed now, would end before the machine stops from the braking
    point of ``deceleration`` (m/s^2). A TC-braking driver then holds the bucket: the pump's load is what brings
    the engine down through the lift-off, and a machine that reaches the braking point with the bucket at the
    dump height meets the shift with the engine held up by the wheels (corners with a 10 m reverse and a 3.5 m
    truck: 1.6-2.6 m/s, 147-190 rad/s, the converter braking up to 2.6 times the limit; measured, stop 38)."""
    to_brake = np.maximum(distance_to_go - stopping_distance(speed, deceleration), 0.0) / np.maximum(speed, LIFT_TIMING_SPEED)
    return lift_time(omega, H, p) < to_brake + speed / deceleration


def lift_time(omega: Any, H: Any, p: LoaderParams) -> Any:
    """s the lift left to the dump height takes at the pump's speed at engine speed ``omega`` (rad/s)."""
    v_lift = lift.max_lift_speed(H, np.maximum(omega, p.omega_min), p)
    return np.maximum(p.H_T - H, 0.0) / np.maximum(v_lift, 1e-3)


def bucket_travel_time(omega: Any, H: Any, V_b: Any, p: LoaderParams) -> Any:
    """s the bucket takes to the dump height from speed ``V_b`` (m/s): at full acceleration up to the pump's
    speed at engine speed ``omega`` (rad/s), on at it, and stopped on the assist's stopping curve. v7's last lift
    clocks it: :func:`lift_time` (the pump's speed alone) fired the last lift late for an idle bucket, which 4 of
    2048 random v7 plans left 2-4 cm short of the dump height (their stop a step earlier than v6's)."""
    ab_lo, ab_hi = p.U_ab_bounds
    v_lift = np.maximum(lift.max_lift_speed(H, np.maximum(omega, p.omega_min), p), 1e-3)
    v0 = np.clip(V_b, 0.0, v_lift)
    speeding_up = (v_lift - v0) ** 2 / (2.0 * ab_hi * v_lift)  # s lost to the acceleration
    stopping = v_lift / (2.0 * BUCKET_STOP_FRACTION * -ab_lo)  # s lost to the stop
    return np.maximum(p.H_T - H, 0.0) / v_lift + speeding_up + stopping


def coasting_deceleration(p: LoaderParams) -> Any:
    """m/s^2 by which a machine in neutral, unbraked, slows: the rolling resistance."""
    return p.F_roll / p.M_tot


def coasting_legs(braking: str) -> tuple[int, ...]:
    """The phases a leg may end early in to coast (WheelLoaderTarget-v3): those the service brakes end (with TC
    braking the converter brakes phase 2, metered from the engine speed: no rolling there)."""
    return (1, 3) if braking == "service" else (3,)


def early_shift(phase: Any, speed: Any, distance_to_go: Any, coast_action: Any, p: LoaderParams, braking: str,
                dt: float) -> Any:
    """Whether the leg ends now to coast (WheelLoaderTarget-v3): at the braking point of the driver's
    coasting fraction of the deceleration limit (``coast_action``: -1 at 15 %, +1 at 95 %,
    :data:`COAST_FRACTION`), in a leg the service brakes end (phase 3; phase 1 with service braking), and only
    where coasting in neutral from now on carries the machine a step's travel past the mark, so the assist
    can always stop it there. A coasting fraction at or above the braking fraction never ends a leg early."""
    lo, hi = COAST_FRACTION
    c = np.clip(np.asarray(coast_action, dtype=float), -1.0, 1.0)
    a_coast = (lo + 0.5 * (c + 1.0) * (hi - lo)) * p.decel_max * p.g
    legs: Any = False
    for leg in coasting_legs(braking):  # (comparisons, not np.isin: ~40x cheaper on the env's step)
        legs = legs | (phase == leg)
    reaches = stopping_distance(speed, coasting_deceleration(p)) >= distance_to_go + speed * dt
    return legs & braking_point(phase, speed, distance_to_go, a_coast, dt) & reaches


def assisted_action(y: Any, phase: Any, distance_to_go: Any, driver: Any, p: LoaderParams, braking: str,
                    dt: float, coast: bool = False, guards: bool = False,
                    lift_floor: bool = False, lift_off_load: bool = False,
                    step_braking: bool = False) -> tuple[Any, Any, Any, Any]:
    """The machine's action (WheelLoaderTarget-v1's: engine-speed request, bucket, brake, shift, each in
    [-1, 1]) for the driver's (request, bucket, braking fraction) at state ``y`` = (omega, V, H, V_b, ...)
    in ``phase``. Floats or arrays of loaders.

    ``coast`` (WheelLoaderTarget-v3): the driver has a fourth action, the coasting fraction at whose braking
    point the leg ends (:func:`early_shift`), and the service brakes act only from the braking point at the
    braking fraction on: the machine coasts in neutral until then (the fuel-optimal cycles do this).
    ``guards`` (WheelLoaderTarget-v4): the creep floor, the last lift and, with TC braking, the lift timing
    (module docstring). ``lift_floor`` (WheelLoaderTarget-v5): the engine-speed floor under a lifting bucket.
    ``lift_off_load`` (WheelLoaderTarget-v6): with TC braking, the guards' lift loads an engine above its metered
    speed at full acceleration whatever the bucket's speed (v4: only a bucket slower than ``IDLE_BUCKET_SPEED``).
    ``step_braking`` (WheelLoaderTarget-v7): the braking asks :func:`step_braking_deceleration` of the driver's
    braking fraction, not the constant deceleration that stops on the mark."""
    request_action, bucket_action, fraction_action = (np.clip(np.asarray(a, dtype=float), -1.0, 1.0) for a in driver[:3])
    V, H, V_b = y[1], y[2], y[3]
    speed = np.abs(V)
    a_limit = p.decel_max * p.g
    lo_f, hi_f = BRAKING_FRACTION
    a_plan = (lo_f + 0.5 * (fraction_action + 1.0) * (hi_f - lo_f)) * a_limit
    shift = braking_point(phase, speed, distance_to_go, a_plan, dt)
    if coast:
        shift = shift | early_shift(phase, speed, distance_to_go, driver[3], p, braking, dt)
    if guards:  # a leg standing on its mark ends (the braking point needs a moving machine)
        shift = shift | (((phase == 1) | (phase == 3)) & (speed < MIN_MOVING_SPEED) & (np.abs(distance_to_go) <= DISTANCE_TOL))
    braking_phase = np.where(shift, phase + 1, phase)
    in_braking = (braking_phase == 2) | (braking_phase == 4)
    a_req = np.where(in_braking, (step_braking_deceleration(speed, distance_to_go, a_plan, p, dt) if step_braking
                                  else stopping_deceleration(speed, distance_to_go, p)), 0.0)
    brake_acts = (braking_phase == 4) | ((braking_phase == 2) & (braking == "service"))
    if coast:  # coast in neutral until braking at the driver's fraction would stop the machine on the mark
        brake_acts = brake_acts & (stopping_distance(speed, a_plan) >= distance_to_go - speed * dt)
    brake = np.where(brake_acts, brake_torque(a_req, p), 0.0)

    request = request_action
    if guards:  # the creep floor: a machine crawling or standing short of its mark moves on
        crawling = ((phase == 1) | (phase == 3)) & ~shift & (speed < CREEP_SPEED) & (distance_to_go > DISTANCE_TOL)
        if np.any(crawling):
            floor = encode_speed_request(creep_speed(p, braking), p)
            request = np.where(crawling, np.maximum(request, floor), request)
    ab_lo, ab_hi = p.U_ab_bounds
    asked = 0.5 * (ab_hi + ab_lo) + bucket_action * 0.5 * (ab_hi - ab_lo)
    metered: Any = np.False_  # (a numpy bool: ~False is -1)
    if braking == "tc":  # the converter metered by the engine speed: in phase 2, and eased into before it
        lift_off = (phase == 1) & ~shift & (stopping_distance(speed, a_plan) + speed * TC_LIFT_OFF_TIME >= distance_to_go)
        metered = (braking_phase == 2) | lift_off
        if np.any(metered):
            lift_off_aim = np.minimum(a_plan, (TC_LIFT_OFF_FRACTION if guards else TC_MAX_FRACTION) * a_limit)
            aim = np.where(braking_phase == 2, np.minimum(a_req, TC_MAX_FRACTION * a_limit), lift_off_aim)
            omega = tc_braking_speed(V, H, V_b, aim, p, braking)
            request = np.where(metered, encode_speed_request(omega, p), request)
            if guards:  # load an engine above its metered speed with the lift the driver leaves idle (v6: any lift)
                slow = True if lift_off_load else V_b < IDLE_BUCKET_SPEED
                asked = np.where(metered & slow & (y[0] > omega), ab_hi, asked)
        if guards:  # keep the lift for the braking
            hold = (phase == 1) & ~metered & lift_done_early(y[0], speed, H, distance_to_go, a_plan, p)
            asked = np.where(hold, -V_b / dt, asked)

    if guards:  # the lift finished at the stop: lift on through the last braking where the lift left would outlast it
        outlasts = (bucket_travel_time(y[0], H, V_b, p) > stopping_time(speed, distance_to_go, a_plan) if step_braking
                    else lift_time(y[0], H, p) > speed / np.maximum(a_req, 1e-3))
        late = (braking_phase == 4) & (p.H_T - H > HEIGHT_TOL) & outlasts
        asked = np.where(late, ab_hi, asked)

    u_ab = bucket_command(H, V_b, asked, p, dt)
    if lift_floor:  # the lift's load rises within the step, faster than the governor's metering sees
        lifting = ((u_ab > 0.0) | (V_b > IDLE_BUCKET_SPEED)) & ~metered  # (a metered engine: >= TC_SPEED_FLOOR omega_min)
        request = np.where(lifting, np.maximum(request, encode_speed_request(LIFT_ENGINE_FLOOR * p.omega_min, p)), request)
    bucket = (u_ab - 0.5 * (ab_hi + ab_lo)) / (0.5 * (ab_hi - ab_lo))
    return request, bucket, 2.0 * brake / p.U_b_max - 1.0, np.where(shift, 1.0, -1.0)
