"""wheel-loader-gym: the wheel loader's short loading cycle as a Gymnasium environment.

``import wl_env`` registers ``WheelLoader-v1`` (single env, and a native vector entry point for
``gymnasium.make_vec(..., vectorization_mode="vector_entry_point")``).
"""

from gymnasium.envs.registration import register, registry

from wl_env.params import DEFAULT_PARAMS, LoaderParams

__version__ = "0.1.0"
__all__ = ["LoaderParams", "DEFAULT_PARAMS", "__version__"]

if "WheelLoader-v1" not in registry:
    register(
        id="WheelLoader-v1",
        entry_point="wl_env.env:WheelLoaderEnv",
        vector_entry_point="wl_env.vector_env:WheelLoaderVectorEnv",
    )
