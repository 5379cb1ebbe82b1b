"""A short receding horizon: the next ``steps`` steps of the cycle's schedule, and the cycle's value beyond.

The full-horizon MPC solves the whole rest of the cycle every step (75-130 steps). A short horizon solves
only its next steps; where it ends inside a phase, the rest of the cycle is priced by a terminal cost from
the last full plan (the OCP on the grid: the cycle's first plan, or a re-plan where the plant estimate
moved): that plan's value to second order about its state at the horizon's end. Its first-order part is
the plan's costate there, the multipliers of the plan's shooting row and state bounds at that step, so
the plan's own steps are an optimum of the short NLP too (the KKT conditions hold with the same
multipliers); the second-order part is a tuning weight (a curvature the grid's value does not give
cheaply), which keeps a plant off the plan from leaving the region where the first-order part holds.
Where the horizon reaches the cycle's end, it is the full NLP with at most ``steps`` slots per phase.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from mpc.controller.grid import N_X, N_XR, U_SCALE, X_SCALE, GridNLP


def horizon_counts(counts: dict[int, int], phase: int, steps: int) -> tuple[dict[int, int], int | None]:
    """The schedule of the next ``steps`` steps (full steps, and the stop steps of phases 2 and 4) of the
    remaining schedule ``counts`` from ``phase`` on, and the phase it ends open in (None: it reaches the
    cycle's end). A phase with no full step left is taken whole (its stop step alone cannot end open), and
    so is one that would end open just before its stop step (one step more)."""
    if steps < 1:
        raise ValueError(f"a horizon needs at least 1 step, got {steps!r}")
    out: dict[int, int] = {}
    taken = 0
    for q in range(phase, 5):
        n, stop = int(counts.get(q, 0)), 1 if q in (2, 4) else 0
        # a phase is taken whole where it fits, has no full step left, or would end open just before its
        # stop step (whose target the terminal cost holds to first order only: measured 8.6 mm off, past
        # the plan's 6.6 mm tolerance, and the re-plan then added a step)
        m = max(steps - taken, 1)  # the phase's steps if it ends open (at least one)
        if taken + n + stop <= steps or n == 0 or (stop and m >= n):
            out[q] = n
            taken += n + stop
            continue
        out[q] = m  # (< n: the phase does not fit whole)
        return out, q
    return out, None


@dataclass
class HorizonReference:
    """A full plan (a solution of the full NLP ``nlp`` for ``counts``), as the warm start and the
    terminal cost of the short horizons along it."""

    nlp: GridNLP
    counts: dict[int, int]
    z: np.ndarray
    lam_x: np.ndarray
    lam_g: np.ndarray
    estimate: np.ndarray  # the plant estimate the plan was made with

    def slots_for(self, counts: dict[int, int], remaining: dict[int, int], open_phase: int | None) -> list[int]:
        """The plan's slots for a horizon's steps: in each phase, the first ``counts[q]`` of the
        ``remaining[q]`` full steps left (the last ones of the plan's), then the stop step, unless the
        horizon ends open in that phase."""
        active = self.nlp.active_slots(self.counts)
        out = []
        for q, n in counts.items():
            full = [k for k in active if self.nlp.slots[k].phase == q and self.nlp.slots[k].kind == "full"]
            left = full[max(len(full) - int(remaining.get(q, 0)), 0):]
            out.extend(left[:n])
            if len(left) < n:  # (the plant is behind the plan here: its last step stands in)
                out.extend(left[-1:] * (n - len(left)))
            if q != open_phase and q in self.nlp.stop_phases:
                out.append(next(k for k in active if self.nlp.slots[k].phase == q and self.nlp.slots[k].kind == "stop"))
        return out

    def warm_start(self, nlp: GridNLP, counts: dict[int, int], remaining: dict[int, int], x_start: np.ndarray,
                   previous: tuple[GridNLP, Any] | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        """Variables and multipliers for the horizon's NLP (``counts``) from the measured start: the steps
        the ``previous`` horizon's solve (its NLP and :class:`~mpc.controller.solver.Solve`) shares with
        this one (all but its first, where the plant kept to the schedule), the plan's for the others;
        and the plan's slot at the horizon's end."""
        mine, theirs = nlp.active_slots(counts).tolist(), self.slots_for(counts, remaining, nlp.open_phase)
        if len(mine) != len(theirs):
            raise ValueError(f"the horizon has {len(mine)} steps, the plan {len(theirs)} for them")
        sources = [(self.nlp, self.z, self.lam_x, self.lam_g, r) for r in theirs]
        if previous is not None and previous[1].z is not None:
            p_nlp, p_sol = previous
            shared = p_nlp.active_slots(p_sol.counts).tolist()[1:len(mine) + 1]
            if [_kind(p_nlp, k) for k in shared] == [_kind(nlp, k) for k in mine[:len(shared)]]:
                sources[:len(shared)] = [(p_nlp, p_sol.z, p_sol.lam_x, p_sol.lam_g, k) for k in shared]
        controls = {k: z[n.slots[r].u:n.slots[r].u + 3] * U_SCALE for k, (n, z, _, _, r) in zip(mine, sources, strict=True)}
        states = {k: z[n.slots[r].x:n.slots[r].x + N_X] * X_SCALE for k, (n, z, _, _, r) in zip(mine, sources, strict=True)}
        z0 = nlp.initial_guess(x_start, counts, controls, states)
        lam_x, lam_g = np.zeros(nlp.n_var), np.zeros(nlp.n_con)
        for k, (n, z, lx, lg, r) in zip(mine, sources, strict=True):  # (the same phase and kind: the same layout)
            (v, gap, rows), (rv, rgap, rrows) = nlp.slot_spans(k), n.slot_spans(r)
            z0[v], lam_x[v], lam_g[gap], lam_g[rows] = z[rv], lx[rv], lg[rgap], lg[rrows]
        return z0, lam_x, lam_g, int(theirs[-1])

    def terminal(self, slot: int) -> tuple[np.ndarray, np.ndarray]:
        """The plan's end state of ``slot`` (scaled, N_XR) and the value's gradient there: minus the
        multipliers of its shooting row and of its bounds (stationarity of the full NLP in that state)."""
        _, gap, _ = self.nlp.slot_spans(slot)
        x = self.nlp.slots[slot].x
        return self.z[x:x + N_XR].copy(), -(self.lam_g[gap] + self.lam_x[x:x + N_XR])


def terminal_arguments(nlp: GridNLP, args: dict[str, Any], ref: HorizonReference, end_slot: int,
                       weight: float) -> dict[str, Any]:
    """``args`` with the terminal cost at the plan's slot ``end_slot`` (an open NLP), else unchanged."""
    if nlp.open_phase is None:
        return args
    x_ref, gradient = ref.terminal(end_slot)
    return nlp.with_terminal(args, x_ref, gradient, weight)


def _kind(nlp: GridNLP, k: int) -> tuple[int, str]:
    return nlp.slots[k].phase, nlp.slots[k].kind
