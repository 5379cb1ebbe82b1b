"""Physical components of the wheel loader, one module each (engine, torque converter, lift, driveline).

Every function works on Python floats, numpy arrays and CasADi symbols alike (see ``backend``).
"""

from wl_env.physics import driveline, engine, lift, torque_converter

__all__ = ["engine", "torque_converter", "lift", "driveline"]
