"""Genetic algorithm and the paper's hybrid GA (HGA: GA, then a local least-squares/SQP polish).

Real-coded GA, vectorised: a whole generation is scored in one population call of the residual
function. Settings follow the seed (section V, MATLAB ``ga``): population 100, 8 elite, crossover
fraction 0.7, mutation probability 0.1 per gene, 3000 generations at most, bounded search box; the run
stops early when the best cost stalls (MATLAB's MaxStallGenerations / FunctionTolerance rule).

Operators (decisions where the paper is silent, docs/identification.md): tournament selection of 2 on
rank; extended intermediate crossover (BLX-0.25) per gene; Gaussian mutation whose width follows the
spread of the best quarter of the population (at least ``min_step`` of the box), reflected at the box.
Works in unit-cube coordinates of the box, so mm and rad parameters are commensurable.
"""

from __future__ import annotations

import time

import numpy as np

from pmcal.calib.solvers.base import Callback, Counter, StallMonitor, finalize, from_unit, initial_population
from pmcal.calib.solvers.local import lsq_polish, sqp_polish
from pmcal.calib.solvers.problem import Problem
from pmcal.calib.solvers.result import IdentResult


def _reflect(U: np.ndarray) -> np.ndarray:
    """Fold unit-cube coordinates back into [0, 1] (mirror at the faces)."""
    U = np.mod(U, 2.0)
    return np.where(U > 1.0, 2.0 - U, U)


def evolve(problem: Problem, counter: Counter, rng: np.random.Generator, *, pop_size: int = 100,
           elite: int = 8, crossover: float = 0.7, mutation: float = 0.1, max_gen: int = 3000,
           stall_gen: int = 50, tol: float = 1e-6, min_step: float = 1e-6,
           callback: Callback | None = None) -> tuple[np.ndarray, float, int, str, list[float]]:
    """Run the GA. Returns (best x, best cost, generations, stop reason, best-cost history)."""
    if not 0 <= elite < pop_size:
        raise ValueError(f"elite count must be in 0..{pop_size - 1}, got {elite}")
    U = initial_population(problem, pop_size, rng)
    F = counter.cost(from_unit(problem, U))
    monitor = StallMonitor(stall_gen, tol)
    n_kids = pop_size - elite
    n_cross = int(round(crossover * n_kids))
    n_mut = n_kids - n_cross
    reason = f"reached {max_gen} generations"
    gen = 0
    for gen in range(1, max_gen + 1):
        order = np.argsort(F)
        U, F = U[order], F[order]
        if monitor.update(F[0]):
            reason = f"stalled: best cost changed by less than {tol:g} (relative) in {stall_gen} generations"
            break
        if callback is not None and callback(gen, float(F[0])):
            reason = "stopped by callback"
            break
        parents = rng.integers(0, pop_size, size=(2 * n_cross + n_mut, 2)).min(axis=1)  # tournament on rank
        a, b = U[parents[:n_cross]], U[parents[n_cross:2 * n_cross]]
        kids_c = a + rng.uniform(-0.25, 1.25, a.shape) * (b - a)
        m = U[parents[2 * n_cross:]]
        width = np.maximum(U[: max(pop_size // 4, 2)].std(axis=0), min_step)
        mask = rng.random(m.shape) < mutation
        mask[np.arange(n_mut), rng.integers(0, problem.n, n_mut)] = True               # at least one gene
        kids_m = m + mask * rng.normal(0.0, 1.0, m.shape) * width
        kids = _reflect(np.concatenate([kids_c, kids_m]))
        U = np.concatenate([U[:elite], kids])
        F = np.concatenate([F[:elite], counter.cost(from_unit(problem, kids))])
    best = int(np.argmin(F))
    return from_unit(problem, U[best]), float(F[best]), gen, reason, monitor.history


def ga(problem: Problem, *, seed: int | None = None, pop_size: int = 100, elite: int = 8,
       crossover: float = 0.7, mutation: float = 0.1, max_gen: int = 3000, stall_gen: int = 50,
       tol: float = 1e-6, callback: Callback | None = None) -> IdentResult:
    """The genetic algorithm alone (paper section VI-B 1)."""
    t0 = time.perf_counter()
    c = Counter(problem)
    x, f, gen, reason, hist = evolve(problem, c, np.random.default_rng(seed), pop_size=pop_size, elite=elite,
                                     crossover=crossover, mutation=mutation, max_gen=max_gen,
                                     stall_gen=stall_gen, tol=tol, callback=callback)
    return finalize(problem, x, "ga", t0, n_eval=c.n, n_iter=gen, success=np.isfinite(f), message=reason,
                    info={"history": hist})


def hga(problem: Problem, *, seed: int | None = None, pop_size: int = 100, elite: int = 8,
        crossover: float = 0.7, mutation: float = 0.1, max_gen: int = 3000, stall_gen: int = 10,
        tol: float = 1e-2, polish: str = "lsq", callback: Callback | None = None) -> IdentResult:
    """The paper's hybrid GA: GA to the basin of the optimum, then a local polish from the GA's best.

    The GA phase stops once it stalls at the coarser ``tol`` (less than 1 % relative cost change over
    10 generations by default): finding the basin is its job, the polish does the rest. (On the paper's
    problem 1e-3 over 20 generations doubles the GA phase and ends at the same optimum:
    docs/identification.md.) ``polish``: ``"lsq"``
    (trust-region least squares, default) or ``"sqp"`` (SLSQP on the chi-square, as the paper's fmincon).
    """
    if polish not in ("lsq", "sqp"):
        raise ValueError(f"polish must be 'lsq' or 'sqp', got {polish!r}")
    t0 = time.perf_counter()
    c = Counter(problem)
    x_ga, f_ga, gen, reason, hist = evolve(problem, c, np.random.default_rng(seed), pop_size=pop_size,
                                           elite=elite, crossover=crossover, mutation=mutation,
                                           max_gen=max_gen, stall_gen=stall_gen, tol=tol, callback=callback)
    n_ga = c.n
    res = lsq_polish(c, x_ga) if polish == "lsq" else sqp_polish(c, x_ga)
    f = float(problem.cost(res.x))
    x = res.x if f <= f_ga else x_ga
    return finalize(problem, x, "hga", t0, n_eval=c.n, n_iter=gen, success=bool(np.isfinite(f)),
                    message=f"GA {reason}; polish: {res.message}",
                    info={"history": hist, "ga_cost": f_ga, "ga_x": x_ga, "ga_evals": n_ga,
                          "polish": polish, "polish_evals": c.n - n_ga})
