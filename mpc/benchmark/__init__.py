"""The yardstick: the multi-phase OCP (minimum time, minimum fuel, the Pareto front), its verification by
re-simulation, and the scoring of any run against it. Independent of the MPC controller."""
