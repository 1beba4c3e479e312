"""Particle swarm optimisation (paper section VI-B 4), vectorised over the swarm.

Global-best PSO with constriction coefficients (Clerc & Kennedy 2002: inertia 0.7298, c1 = c2 = 1.49618)
in unit-cube coordinates of the search box; velocities clamped to ``vmax`` of the box per step,
positions reflected at the faces. Stops when the best cost stalls (as the GA) or after ``max_iter``.
No PSO in scipy; pymoo's is an optional dependency, so this is hand-written (benchmarks/identify_bench.py).
"""

from __future__ import annotations

import time

import numpy as np

from pmcal.calib.solvers.base import Callback, Counter, StallMonitor, finalize, from_unit, initial_population
from pmcal.calib.solvers.ga import _reflect
from pmcal.calib.solvers.problem import Problem
from pmcal.calib.solvers.result import IdentResult


def pso(problem: Problem, *, seed: int | None = None, swarm: int = 100, inertia: float = 0.7298,
        c1: float = 1.49618, c2: float = 1.49618, vmax: float = 0.2, max_iter: int = 3000,
        stall_gen: int = 50, tol: float = 1e-6, callback: Callback | None = None) -> IdentResult:
    """Minimise the problem's chi-square with a particle swarm."""
    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    c = Counter(problem)
    U = initial_population(problem, swarm, rng)
    V = rng.uniform(-vmax, vmax, U.shape)
    F = c.cost(from_unit(problem, U))
    P, PF = U.copy(), F.copy()
    monitor = StallMonitor(stall_gen, tol)
    reason, it = f"reached {max_iter} iterations", 0
    for it in range(1, max_iter + 1):
        g = int(np.argmin(PF))
        if monitor.update(PF[g]):
            reason = f"stalled: best cost changed by less than {tol:g} (relative) in {stall_gen} iterations"
            break
        if callback is not None and callback(it, float(PF[g])):
            reason = "stopped by callback"
            break
        r1, r2 = rng.random(U.shape), rng.random(U.shape)
        V = np.clip(inertia * V + c1 * r1 * (P - U) + c2 * r2 * (P[g] - U), -vmax, vmax)
        U = _reflect(U + V)
        F = c.cost(from_unit(problem, U))
        better = F < PF
        P[better], PF[better] = U[better], F[better]
    g = int(np.argmin(PF))
    return finalize(problem, from_unit(problem, P[g]), "pso", t0, n_eval=c.n, n_iter=it,
                    success=bool(np.isfinite(PF[g])), message=reason, info={"history": monitor.history})
