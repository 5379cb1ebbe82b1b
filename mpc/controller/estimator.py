"""The MPC's model-error estimator: how the plant differs from the model, from one-step prediction errors.

* dV/dt = gain * (model's dV/dt) + d * offset: a payload error scales the acceleration of every force
  (gain = model mass / plant mass); a rolling-resistance error is an acceleration against the travel
  direction (offset). Phase 1 varies the model's acceleration enough to tell them apart, so the braking
  phases start with the plant's deceleration per unit of brake or converter torque, not the nominal one.
  Steps that stop, reverse or change phase say nothing about it.
* The lift's power drawn from the engine is proportional to the payload (eq. (10)), so a payload error
  also shows in the engine's acceleration: d omega/dt = model - (lift_gain - 1) P_lift / (omega J_ice).
  With TC braking the engine speed at the shift sets the converter's drag, so a plan must predict it to
  the rad/s.
* Steps at the governor's cap with the lift moving say nothing of the acceleration either (the comment in
  :meth:`ModelErrorEstimator.update`).
* Until the lift has loaded the engine enough to tell (its data weighing as much as the prior), the lift
  gain is the one the acceleration gain implies if the payload makes the whole mass error (a wheel loader's
  payload varies from cycle to cycle, its own mass does not), fused with the prior by their variances. The
  optimum holds the bucket while the engine runs up, so the lift is seen only late in phase 1; by then a TC
  plan for the nominal lift has brought the engine too high to come down by the shift (measured: a TC draw at
  payload x0.81 and rolling resistance x1.26 ended 0.21 m past its reversing point, stop 57). The link is
  taken only while the bucket stands still: a moving lift's load enters the acceleration the gain is regressed
  on, and the two fed each other (a service draw's gain drifted 0.7 % off, its braking 0.37 % over the limit).

Both are recursive least squares with forgetting over the steps so far. The estimator also keeps the
moving RMS of the plans' one-step engine-speed error, from which the controller sizes its margins.
"""

from __future__ import annotations

import math

import numpy as np

from mpc.controller.grid import StepModel
from wl_env.simulator import Simulator

# [gain, offset m/s^2]: prior, its spread (a payload or mass error of ~20 %, a rolling-resistance error of
# ~0.3 m/s^2), bounds, forgetting.
THETA_PRIOR = np.array([1.0, 0.0])
THETA_PRIOR_STD = np.array([0.2, 0.3])
THETA_MIN, THETA_MAX = np.array([0.5, -1.0]), np.array([1.5, 1.0])
RLS_FORGETTING = 0.98
ACCEL_NOISE_STD = 0.01  # m/s^2: how well one step of the model predicts the measured acceleration
# Lift-load gain (plant payload / model payload, as the lift's power drawn from the engine shows it):
# prior, spread, bounds, and how well one step of the model predicts the engine's acceleration.
LIFT_GAIN_PRIOR, LIFT_GAIN_PRIOR_STD = 1.0, 0.2
LIFT_GAIN_MIN, LIFT_GAIN_MAX = 0.5, 1.5
ENGINE_ACCEL_NOISE_STD = 1.0  # rad/s^2
LIFT_GAIN_PROBE = 1e-3  # the step in the lift gain of the engine-speed slope's forward difference
STILL_BUCKET_SPEED = 0.01  # m/s: below it the lift draws no power to speak of
PREDICTION_ERROR_DECAY = 0.9  # per step, of the moving mean square of the one-step prediction error


class ModelErrorEstimator:
    """Estimates [accel gain, accel offset] and the lift gain of the plant against ``model``."""

    def __init__(self, model: StepModel, dt: float) -> None:
        self.model, self.dt = model, float(dt)
        self.params = model.params
        self._sim = Simulator(model.params, model.braking)  # the machine's saturations of the applied control
        self.reset()

    def reset(self) -> None:
        self.theta = THETA_PRIOR.copy()
        self._theta_cov = np.diag(THETA_PRIOR_STD**2)
        self.lift_gain, self._lift_gain_var = LIFT_GAIN_PRIOR, LIFT_GAIN_PRIOR_STD**2
        self._lift_information = 0.0  # the engine-speed data's information on the lift gain so far (1 / gain^2)
        self._bucket_still = True  # the bucket has not moved yet (the lift gain then follows the mass)
        self._omega_err2 = 0.0  # moving mean square of the plans' one-step engine-speed error (rad/s)^2

    @property
    def estimate(self) -> np.ndarray:
        """The plant estimate as the grid model takes it: [accel offset, accel gain, lift gain]."""
        return np.array([self.theta[1], self.theta[0], self.lift_gain])

    @property
    def omega_error_rms(self) -> float:
        return math.sqrt(self._omega_err2)

    def track_prediction(self, measured_omega: float, predicted_omega: float) -> None:
        """The plan's one-step engine-speed error (moving RMS)."""
        e = measured_omega - predicted_omega
        self._omega_err2 = PREDICTION_ERROR_DECAY * self._omega_err2 + (1.0 - PREDICTION_ERROR_DECAY) * e * e

    def update(self, x0: np.ndarray, phase0: int, u: np.ndarray, x: np.ndarray, phase: int) -> None:
        """One step of the plant, from x0 in phase0 under the commanded control u to x in phase."""
        if phase0 != phase:
            return
        p, dt = self.params, self.dt
        y = (float(x0[0]), float(x0[1]), float(x0[2]), float(x0[3]), 0.0, 0.0)
        ue = self._sim.effective_controls(y, phase0, float(u[0]), float(u[1]), float(u[2]), dt)[:3]
        lifting = max(abs(x0[3]), abs(x[3])) >= STILL_BUCKET_SPEED
        self._bucket_still = self._bucket_still and not lifting
        capped = max(x0[0], x[0]) >= 0.99 * p.omega_max
        if not capped:  # at the governor's cap the fuel, not the load, sets omega
            # Linearized at the estimate: omega(g) = omega(g_hat) + (g - g_hat) r dt, r the local slope. (Not the
            # secant from g = 0 to 1: omega is convex in g, the lift's load slowing the engine, and the secant
            # settled a plant of payload x1.2 at 1.22, the engine then 0.1-0.4 rad/s per step faster than planned.)
            omega_hat, _ = self.predict(x0, phase0, ue, self.lift_gain, self.theta)
            omega_up, _ = self.predict(x0, phase0, ue, self.lift_gain + LIFT_GAIN_PROBE, self.theta)
            r = (omega_up - omega_hat) / (LIFT_GAIN_PROBE * dt)
            residual = (x[0] - omega_hat) / dt  # measured minus modelled d omega/dt
            var = self._lift_gain_var
            k = var * r / (RLS_FORGETTING * ENGINE_ACCEL_NOISE_STD**2 + r * var * r)
            self.lift_gain += k * residual
            self._lift_gain_var = (var - k * r * var) / RLS_FORGETTING
            self.lift_gain = min(max(self.lift_gain, LIFT_GAIN_MIN), LIFT_GAIN_MAX)
            self._lift_information += (r / ENGINE_ACCEL_NOISE_STD) ** 2
        # (capped and lifting: the plant's governor metered the injection for its own lift load, which the model's
        # saturations here do not know; such steps pulled a service draw's gain 0.6 % off in 10 steps, the
        # braking after them 0.05-0.2 % over the limit, measured at stop 57)
        if abs(x0[1]) >= 0.2 and abs(x[1]) >= 0.2 and not (capped and lifting):
            # the model's mean dV/dt over the step, its engine speed as the lift-load estimate has it
            _, v1 = self.predict(x0, phase0, ue, self.lift_gain, THETA_PRIOR)
            d = -1.0 if phase0 <= 2 else 1.0
            regressor = np.array([(v1 - x0[1]) / dt, d])
            measured = (x[1] - x0[1]) / dt
            P = self._theta_cov
            k = P @ regressor / (RLS_FORGETTING * ACCEL_NOISE_STD**2 + regressor @ P @ regressor)
            self.theta = self.theta + k * (measured - regressor @ self.theta)
            self._theta_cov = (P - np.outer(k, regressor @ P)) / RLS_FORGETTING
            self.theta = np.clip(self.theta, THETA_MIN, THETA_MAX)
            if self._bucket_still and self._lift_information < 1.0 / LIFT_GAIN_PRIOR_STD**2:  # (the payload's mass)
                self.lift_gain, self._lift_gain_var = self.lift_gain_from_mass()

    def lift_gain_from_mass(self) -> tuple[float, float]:
        """The lift gain and its variance from the acceleration gain, the payload taken as the whole mass error
        (plant payload = model payload + model mass (1 / gain - 1)), fused with the prior by their variances."""
        p, gain = self.params, float(self.theta[0])
        if p.M_load <= 0.0:  # (no payload in the model: no ratio to speak of)
            return LIFT_GAIN_PRIOR, LIFT_GAIN_PRIOR_STD**2
        scale = p.M_tot / p.M_load
        implied = 1.0 + scale * (1.0 / gain - 1.0)
        implied_var = (scale / gain**2) ** 2 * float(self._theta_cov[0, 0])  # (the first-order propagation)
        w_prior, w_implied = 1.0 / LIFT_GAIN_PRIOR_STD**2, 1.0 / max(implied_var, 1e-12)
        fused = (w_prior * LIFT_GAIN_PRIOR + w_implied * implied) / (w_prior + w_implied)
        return min(max(fused, LIFT_GAIN_MIN), LIFT_GAIN_MAX), 1.0 / (w_prior + w_implied)

    def predict(self, x0: np.ndarray, phase: int, u: tuple, lift_gain: float, accel: np.ndarray) -> tuple[float, float]:
        """(omega, V) one control step after x0 under the effective controls u, by the plan's own step
        (:class:`mpc.controller.grid.StepModel`) with the lift drawing lift_gain times the model's power
        from the engine and dV/dt = accel[0] * model + d * accel[1]."""
        x1 = self.model.full[phase].fn(np.asarray(x0, dtype=float)[:5], np.asarray(u, dtype=float), self.dt,
                                       np.array([accel[1], accel[0], lift_gain]), self.model.step_scenario)[0]
        return float(x1[0]), float(x1[1])
