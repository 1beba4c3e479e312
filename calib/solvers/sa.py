"""Simulated annealing (paper section VI-B 3) through ``scipy.optimize.dual_annealing``.

Generalised simulated annealing (Tsallis-Stariolo visiting distribution) with the local search switched
off (``no_local_search=True``): plain SA, as the paper compares it. In unit-cube coordinates of the
search box. One parameter set per evaluation (scipy's SA is sequential), so it is the slowest method.
"""

from __future__ import annotations

import time

import numpy as np
from scipy.optimize import dual_annealing

from pmcal.calib.solvers.base import Callback, Counter, finalize, from_unit, to_unit
from pmcal.calib.solvers.problem import Problem
from pmcal.calib.solvers.result import IdentResult


def sa(problem: Problem, *, seed: int | None = None, maxfun: int = 20000, maxiter: int = 1000,
       initial_temp: float = 5230.0, callback: Callback | None = None) -> IdentResult:
    """Minimise the chi-square by simulated annealing within the search box (``maxfun`` evaluations)."""
    t0 = time.perf_counter()
    c = Counter(problem)
    stop = {"it": 0}

    def cb(u, f, context):
        stop["it"] += 1
        return bool(callback(stop["it"], float(f))) if callback is not None else False

    res = dual_annealing(lambda u: float(c.cost(from_unit(problem, u))[0]), bounds=[(0.0, 1.0)] * problem.n,
                         x0=np.clip(to_unit(problem, problem.x0), 0, 1), seed=seed, maxfun=maxfun,
                         maxiter=maxiter, initial_temp=initial_temp, no_local_search=True, callback=cb)
    msg = res.message[0] if isinstance(res.message, (list, tuple)) else str(res.message)
    return finalize(problem, from_unit(problem, res.x), "sa", t0, n_eval=c.n, n_iter=int(res.nit),
                    success=bool(np.isfinite(res.fun)), message=msg)
