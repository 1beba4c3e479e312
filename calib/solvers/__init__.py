"""Identification methods behind one call signature, returning :class:`IdentResult`.

``identify(problem, method="hga", seed=..., **options)`` solves any :class:`Problem` (population-vectorised
least squares, see :mod:`pmcal.calib.solvers.problem`) with one of :data:`METHODS`:

==========  ==================================================================================
hga         the paper's hybrid GA: GA to the basin, then a least-squares (or SQP) polish
ga          the GA alone (paper VI-B)
pso         particle swarm (paper VI-B)
sa          simulated annealing, ``scipy.optimize.dual_annealing`` without local search (paper VI-B)
lm          Levenberg-Marquardt, ``scipy.optimize.least_squares(method="lm")`` (paper VI-B)
tikhonov    linearised model with Tikhonov regularisation and the L-curve corner (paper eq. 18-20)
tsvd        linearised model with truncated SVD (paper 003 eq. 27-29)
==========  ==================================================================================

Before solving, parameters with no first-order effect on the data (:mod:`pmcal.calib.identifiability`,
judged on the problem's noise-free ``design`` or at a quick regularised fit: :func:`reference_point`)
are held at their prior and listed in ``IdentResult.fixed`` (``fix_unidentifiable=False`` keeps them);
``prior_std`` adds a Gaussian prior on every parameter (regularises weakly determined ones).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from pmcal.calib.solvers.ga import ga, hga
from pmcal.calib.solvers.local import lm
from pmcal.calib.solvers.problem import LeastSquaresProblem, Problem, box_problem
from pmcal.calib.solvers.pso import pso
from pmcal.calib.solvers.regularized import tikhonov, tsvd
from pmcal.calib.solvers.result import IdentResult
from pmcal.calib.solvers.sa import sa

SOLVERS: dict[str, Callable[..., IdentResult]] = {
    "hga": hga, "ga": ga, "pso": pso, "sa": sa, "lm": lm, "tikhonov": tikhonov, "tsvd": tsvd,
}
METHODS: tuple[str, ...] = tuple(SOLVERS)


def identify(problem: Problem, method: str = "hga", *, seed: int | None = None,
             fix_unidentifiable: bool = True, prior_std: np.ndarray | float | None = None,
             **options) -> IdentResult:
    """Solve ``problem`` with ``method``; the result lists every parameter of ``problem`` in its order.

    ``options`` go to the method (e.g. ``pop_size``, ``max_gen`` for ``ga``/``hga``; ``lam`` for
    ``tikhonov``; ``rank`` for ``tsvd``; ``callback(iteration, best_cost)`` for the iterative ones).
    """
    if method not in SOLVERS:
        raise ValueError(f"unknown identification method '{method}' (known: {', '.join(METHODS)})")
    from pmcal.calib.identifiability import analyse

    work = problem
    unidentifiable: list[str] = []
    if fix_unidentifiable:
        unidentifiable = analyse(*reference_point(problem)).unidentifiable
        work = problem.fix(unidentifiable)
    if prior_std is not None:
        std = np.broadcast_to(np.asarray(prior_std, float), (problem.n,))
        work = work.with_prior(std[[problem.names.index(k) for k in work.names]])
    res = SOLVERS[method](work, seed=seed, **options)
    res.info["unidentifiable"] = unidentifiable
    return reorder(res, problem.names)


def reference_point(problem: Problem) -> tuple[Problem, np.ndarray]:
    """Where to judge identifiability: the problem's ``design`` at its prior if it has one, else the
    problem at a quick Levenberg-Marquardt fit with a Gaussian prior of one box half-width on every
    parameter.

    At the prior itself the measured data are inconsistent with the model, and that defect lends
    parameters a spurious first-order effect (on the paper's model ``L1.day`` shows 9 noise sigmas at
    the nominal parameters and 0.2 at the solution); without the prior the fit runs far along the
    directions only the noise sees (``L1.day`` to 28 mm), where they gain one. Falls back to the prior
    if the fit fails.
    """
    if problem.design is not None:
        return problem.design, problem.design.x0
    res = lm(problem.with_prior(problem.scale))
    return problem, (res.x if res.success and np.all(np.isfinite(res.x)) else problem.x0)


def reorder(res: IdentResult, names: list[str]) -> IdentResult:
    """The result with parameters (and covariance rows/columns) in the order of ``names``."""
    idx = [res.names.index(k) for k in names]
    res.names = list(names)
    res.x = np.asarray(res.x)[idx]
    res.units = [res.units[i] for i in idx] if res.units else res.units
    if res.covariance is not None:
        res.covariance = res.covariance[np.ix_(idx, idx)]
    return res


__all__ = ["IdentResult", "LeastSquaresProblem", "Problem", "box_problem", "identify", "METHODS", "SOLVERS",
           "reorder"]
