"""wheel-loader-gym: the wheel loader's short loading cycle as a Gymnasium environment.

``import wl_env`` registers ``WheelLoaderPlan-v1`` and ``-v0`` (one plan per cycle, driven on v7 and v6:
:mod:`wl_env.plan`), ``WheelLoaderTarget-v7`` (v6 whose assist brakes on the step grid as the optimum does),
``WheelLoaderTarget-v6`` (v5 whose TC lift-off loads the engine with a full lift),
``WheelLoaderTarget-v5`` (v4 whose assist keeps an idling engine clear of a stall under the lift), ``WheelLoaderTarget-v4`` (v3 whose assist guards the driver: a machine short of
its mark moves on, the lift reaches the dump height, and with TC braking the shift into forward gear keeps the
deceleration limit), ``WheelLoaderTarget-v3`` (v2 whose driver may also end a leg early: the
machine coasts in neutral and the assist brakes late), ``WheelLoaderTarget-v2`` (v1 driven through a stopping assist: the driver
sets the engine-speed request, the bucket and the braking point; the assist stops on the marks),
``WheelLoaderTarget-v1`` (v0 with action 0 an engine-speed request to the
engine's governor), ``WheelLoaderTarget-v0`` (v2 with a target cycle time per episode, observed,
its lateness charged), ``WheelLoader-v2`` (scenarios, the scenario in the observation) and
``WheelLoader-v1`` (the 12-entry observation the shipped policies were trained on), each a single env and
a native vector entry point for ``gymnasium.make_vec(..., vectorization_mode="vector_entry_point")``.
"""

from gymnasium.envs.registration import register, registry

from wl_env.params import DEFAULT_PARAMS, LoaderParams
from wl_env.scenario import Scenario

__version__ = "0.3.2"  # (0.3: WheelLoaderTarget-v7, WheelLoaderPlan-v1; 0.3.1: both plan policies on v1; 0.3.2: the TC one seed 2)
__all__ = ["LoaderParams", "DEFAULT_PARAMS", "Scenario", "__version__"]

_IDS = {
    # v6 whose braking ends on the step grid: its first step takes up the rest, the others run at the plan (wl_env.assist)
    "WheelLoaderTarget-v7": {"observe_scenario": True, "observe_target": True, "w_time": 0.0, "fuel_action": "engine_speed",
                             "assist": True, "coast": True, "guards": True, "lift_floor": True, "lift_off_load": True,
                             "step_braking": True},
    # v5 whose TC lift-off loads the engine with a full lift whatever the bucket's speed (wl_env.assist)
    "WheelLoaderTarget-v6": {"observe_scenario": True, "observe_target": True, "w_time": 0.0, "fuel_action": "engine_speed",
                             "assist": True, "coast": True, "guards": True, "lift_floor": True, "lift_off_load": True},
    # v4 with the lift's engine floor (wl_env.assist: an idling engine stalled under the lift)
    "WheelLoaderTarget-v5": {"observe_scenario": True, "observe_target": True, "w_time": 0.0, "fuel_action": "engine_speed",
                             "assist": True, "coast": True, "guards": True, "lift_floor": True},
    # v3 whose assist guards the driver (creep floor, last lift, TC lift timing: wl_env.assist)
    "WheelLoaderTarget-v4": {"observe_scenario": True, "observe_target": True, "w_time": 0.0, "fuel_action": "engine_speed",
                             "assist": True, "coast": True, "guards": True},
    # v2 whose assist lets the driver end a leg early and coast in neutral, braking late (a 4th action)
    "WheelLoaderTarget-v3": {"observe_scenario": True, "observe_target": True, "w_time": 0.0, "fuel_action": "engine_speed",
                             "assist": True, "coast": True},
    # the target task driven through the stopping assist (wl_env.assist): 3 actions, the marks the assist's
    "WheelLoaderTarget-v2": {"observe_scenario": True, "observe_target": True, "w_time": 0.0, "fuel_action": "engine_speed",
                             "assist": True},
    # the target task with an engine-speed governor: action 0 requests the engine speed (v0: the injection)
    "WheelLoaderTarget-v1": {"observe_scenario": True, "observe_target": True, "w_time": 0.0, "fuel_action": "engine_speed"},
    # a task of its own (not v2's successor: Gymnasium would call v2 out of date): a target cycle time per
    # episode, observed, its lateness charged; time itself costs nothing
    "WheelLoaderTarget-v0": {"observe_scenario": True, "observe_target": True, "w_time": 0.0},
    "WheelLoader-v2": {"observe_scenario": True},
    "WheelLoader-v1": {"observe_scenario": False},
}
for _id, _kwargs in _IDS.items():
    if _id not in registry:
        register(
            id=_id,
            entry_point="wl_env.env:WheelLoaderEnv",
            vector_entry_point="wl_env.vector_env:WheelLoaderVectorEnv",
            kwargs=_kwargs,
        )
# one decision per cycle: a phase-parametric plan driven on WheelLoaderTarget-v6 (v0) or -v7 (v1) (wl_env.plan)
for _id, _cls in (("WheelLoaderPlan-v0", "WheelLoaderPlan"), ("WheelLoaderPlan-v1", "WheelLoaderPlanV1")):
    if _id not in registry:
        register(id=_id, entry_point=f"wl_env.plan:{_cls}Env", vector_entry_point=f"wl_env.plan:{_cls}VectorEnv")
