"""The MPC's schedule: whole control steps per phase, which fix the cycle time, and the search over them.

The first step rounds the continuous optimum's phase durations to steps (:func:`apportion`); then
single-step moves between phases (or a step added or removed) are tried where the parametric
sensitivities of the step lengths (:meth:`mpc.controller.grid.GridNLP.sensitivities`) predict that the
mode's cost falls. A move that did not pay waits before it is tried again.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator

import numpy as np

from mpc.controller.grid import GridNLP
from mpc.controller.solver import Solve

MODES = ("time", "target_time", "weighted")
FUEL_REF_G, TIME_REF = 100.0, 10.0  # the weighted mode's normalization (as the OCP's weighted objective)
# Objective (g) per step in minimum-time mode and per step late in target-time mode: a step outweighs
# any fuel, not a target miss (MISS_TOL_M decides that first).
STEP_PRICE = 1.0e3
RETRY_AFTER = 10  # steps before a move that did not pay is tried again (twice as many after each failure)

Move = tuple[int | None, int | None]  # (phase losing a step or None: one added, phase gaining one or None)


def apportion(durations: dict[int, float], n_steps: int, dt: float) -> dict[int, int]:
    """Whole steps per phase closest to continuous phase durations, ``n_steps`` in all (largest
    remainders), each phase at least one step; returned as full-step counts (without the stop steps)."""
    phases = sorted(durations)
    want = np.array([max(durations[ph], 0.0) / dt for ph in phases])
    if n_steps < len(phases):
        raise ValueError(f"{n_steps} steps cannot hold {len(phases)} phases (at least one step each)")
    want = want * (n_steps / want.sum()) if want.sum() > 0 else np.full(len(phases), n_steps / len(phases))
    steps = np.maximum(np.floor(want).astype(int), 1)
    while steps.sum() > n_steps:
        steps[np.argmax(np.where(steps > 1, steps - want, -np.inf))] -= 1
    while steps.sum() < n_steps:
        steps[np.argmax(want - steps)] += 1
    return {ph: int(n) - (1 if ph in (2, 4) else 0) for ph, n in zip(phases, steps, strict=True)}


def steps_of(counts: dict[int, int]) -> int:
    """Control steps a schedule takes (the stop steps included)."""
    return sum(counts.values()) + sum(1 for ph in counts if ph in (2, 4))


def moved(counts: dict[int, int], move: Move | tuple[Move, Move]) -> dict[int, int]:
    """``counts`` after ``move``, or after each of a compound move's two (MPCController._compound)."""
    if isinstance(move[0], tuple):
        return moved(moved(counts, move[0]), move[1])
    c = dict(counts)
    i, j = move
    if i is not None:
        c[i] -= 1
    if j is not None:
        c[j] += 1
    return c


class ScheduleSearch:
    """How a mode ranks schedules, and which single-step move to try next.

    Modes: the fewest steps (``time``), the least fuel finishing by ``target_steps`` (``target_time``),
    or fuel and time weighed by ``w_fuel`` (``weighted``)."""

    def __init__(self, mode: str, dt: float, w_fuel: float | None = None) -> None:
        if mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
        self.mode, self.dt, self.w_fuel = mode, float(dt), w_fuel
        self.reset()

    def reset(self, target_steps: int = 0) -> None:
        self.target_steps = target_steps
        # The fewest steps a removal may leave (0: no bound; set by bounded()): the first plan's search at minimum time
        # takes it from the continuous reference's T_min (mpc.MPCController._plan_cycle), where a shorter schedule
        # cannot hold the targets, and a removal's solve only finds that out in 0.15-0.3 s.
        self.min_steps = 0
        self.tried: dict[Move, tuple[int, int]] = {}  # move -> (step it last failed to pay, failures)
        self.last_failure = -10**9  # the step a schedule move last failed to pay
        self.failures = 0  # schedule moves in a row that did not pay (each doubles the wait for the next)

    @contextlib.contextmanager
    def bounded(self, min_steps: int) -> Iterator[None]:
        """Within the block, no removal to fewer than ``min_steps`` steps (the first plan's search)."""
        self.min_steps = min_steps
        try:
            yield
        finally:
            self.min_steps = 0

    # ------------------------------------------------------------------ ranking
    def cost(self, sol: Solve, k: int) -> tuple:
        """How the mode ranks a solved schedule: targets met first, then steps and fuel as it weighs them."""
        if not sol.ok:
            return (2, math.inf)
        if not sol.feasible:
            return (1, sol.J)
        return (0, self.scalar_cost(sol.J, steps_of(sol.counts), k))

    def scalar_cost(self, J: float, n_steps: int, k: int) -> float:
        if self.mode == "time":
            return J + STEP_PRICE * n_steps
        if self.mode == "target_time":
            return J + STEP_PRICE * max(k + n_steps - self.target_steps, 0)
        if self.w_fuel == 0.0:
            return J + STEP_PRICE * n_steps
        # weighted: grams of fuel per step of time at the mode's exchange rate
        return J + (1.0 - self.w_fuel) / TIME_REF * self.dt / (self.w_fuel / FUEL_REF_G) * n_steps

    def late(self, sol: Solve, k: int) -> bool:
        return self.mode == "target_time" and k + steps_of(sol.counts) > self.target_steps

    # ------------------------------------------------------------------ moves
    def moves(self, sol: Solve, nlp: GridNLP, phase: int, k: int) -> list[tuple[float, Move]]:
        """Schedule moves of one step, with the change the sensitivities predict, best first.

        A move (i, j) takes a step from phase i and gives it to phase j; i or j None adds or removes one.
        Phases 1 and 3 keep a step until they are under way (each phase lasts >= 0.1 s), and a phase in
        its last step keeps its end (the plan shifts now; one step more at a time runs away past the
        reversing point when the targets are out of reach). The prediction is the mode's cost while the
        schedule meets the targets, else the objective alone (the misses first, whatever the steps).
        """
        sens = nlp.sensitivities(sol.lam_p, sol.counts, self.dt)
        counts, n = sol.counts, steps_of(sol.counts)
        base = self.scalar_cost(sol.J, n, k)
        phases = list(counts)

        def removable(q: int) -> bool:
            return counts[q] > (0 if q in (2, 4) or q == phase else 1)

        def fits(q: int) -> bool:
            return counts[q] < nlp.slots_per_phase[q] and not (q == phase and q in (1, 3) and counts[q] == 0)

        out = []
        for i in [None, *phases]:
            for j in [None, *phases]:
                if i == j or (i is not None and not removable(i)) or (j is not None and not fits(j)):
                    continue
                if j is None and n - 1 < self.min_steps:
                    continue
                dJ = (sens[j] if j is not None else 0.0) - (sens[i] if i is not None else 0.0)
                dn = (j is not None) - (i is not None)
                out.append((self.scalar_cost(sol.J + dJ, n + dn, k) - base if sol.feasible else dJ, (i, j)))
        return sorted(out)

    def candidate(self, sol: Solve, nlp: GridNLP, phase: int, k: int, failed: set, removals: bool,
                  min_gain: float) -> Move | None:
        """The move to try: the best predicted one not tried in vain (``failed``, or within RETRY_AFTER
        steps); while the targets are missed, the one predicted to cut the misses most, never a removal."""
        for gain, move in self.moves(sol, nlp, phase, k):
            last, failures = self.tried.get(move, (-10**9, 0))
            if move in failed or k - last < RETRY_AFTER * 2 ** max(failures - 1, 0):
                continue
            if move[1] is None and (not removals or not sol.feasible):
                continue
            return move if gain < -min_gain else None
        return None

    def waiting(self, k: int) -> bool:
        """A move failed to pay recently: wait RETRY_AFTER steps, twice as long after each such move in a
        row (a schedule too short fails slowly: 0.2-0.6 s), so a nominal cycle tries 3-4."""
        return k - self.last_failure < RETRY_AFTER * 2 ** max(self.failures - 1, 0)

    def hold(self, move: Move, k: int) -> None:
        """Do not try ``move`` for RETRY_AFTER steps from step k, as if it had failed once then (the schedule
        just moved the other way for a reason the search does not see), leaving the other moves' waits alone."""
        self.tried[move] = (k, max(self.tried.get(move, (0, 0))[1], 1))

    def record(self, move: Move, k: int, paid: bool) -> None:
        if paid:
            self.failures = 0
        else:
            self.tried[move] = (k, self.tried.get(move, (0, 0))[1] + 1)
            self.last_failure, self.failures = k, self.failures + 1
