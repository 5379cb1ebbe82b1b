"""The receding-horizon MPC that drives the environment, on the environment's own control grid."""
