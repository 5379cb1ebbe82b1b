"""wheel-loader-gym: the wheel loader's short loading cycle as a Gymnasium environment.

``import wl_env`` registers ``WheelLoader-v2`` (scenarios, the scenario in the observation) and
``WheelLoader-v1`` (the 12-entry observation the shipped policies were trained on), each a single env and
a native vector entry point for ``gymnasium.make_vec(..., vectorization_mode="vector_entry_point")``.
"""

from gymnasium.envs.registration import register, registry

from wl_env.params import DEFAULT_PARAMS, LoaderParams
from wl_env.scenario import Scenario

__version__ = "0.2.0"
__all__ = ["LoaderParams", "DEFAULT_PARAMS", "Scenario", "__version__"]

for _version, _observe in (("v2", True), ("v1", False)):
    if f"WheelLoader-{_version}" not in registry:
        register(
            id=f"WheelLoader-{_version}",
            entry_point="wl_env.env:WheelLoaderEnv",
            vector_entry_point="wl_env.vector_env:WheelLoaderVectorEnv",
            kwargs={"observe_scenario": _observe},
        )
