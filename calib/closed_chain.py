"""Identification, identifiability, CRLB and compensation of any closed-chain machine (a :class:`ChainModel`).

The machine is reached only through :class:`pmcal.calib.chain_model.ChainModel` (the twin's
:class:`pmcal.twin.closed_chain.ClosedChainTwin`, or another simulator): its exact identification
Jacobian ``d targets / d errors`` is all this module needs.

**Identifiability and the base set** (:func:`base_parameters`). The identification Jacobian, whitened by the
tracker noise and with each column scaled by the error's prior size (so mm and deg compare), is reduced as
figaroh does for serial robots (D. V. T. Nguyen, V. Bonnet et al., FIGAROH, 2023; github.com/thanhndv212/figaroh,
``tools/qrdecomposition.py``: ``get_baseIndex`` / ``get_baseParams``): a QR decomposition with column
pivoting ``J P = Q R`` of the column-normalised Jacobian gives the base parameters (the first ``r`` pivots,
``r`` the number of singular values of the scaled Jacobian above ``rank_tol`` times the largest: the
directions along which prior-sized errors move the readings by more than that share of the most visible
one; a count of ``|R_ii|`` above a tolerance would depend on the pivot order where a CAD model's directions
thin out without a gap, and the pivot order on the last bits: talos gave 30 and 32); the others are linear
combinations of them, ``J_dep = J_base B`` with ``B = R^-1 Q^T J_dep`` (rescaled to the parameters'
units). Equivalent errors (a frame's offset and its child's) tie exactly for a pivot; LAPACK's ``geqp3``
breaks such a tie by the last bits of the norms, which differ between BLAS kernels (another base set,
prior and predicted uncertainty on an AMD EPYC than on an Intel CPU), so the pivoting is done here with
ties (:data:`TIE_TOL`) going to the first key. A base parameter's identified value estimates the
*combination* ``p_i + sum_j B_ij p_j`` (written out in words, e.g. ``"rod1a.dz + 1 rod1a_tip.dz"``), and each
dependent parameter ``j`` spans a direction ``e_j - sum_i B_ij e_i`` the data cannot see (listed in
``unidentifiable``).

**Estimation** (:func:`identify_chain`): the base parameters by Levenberg-Marquardt
(:func:`pmcal.calib.solvers.local.lm`, MINPACK through scipy) on the whitened target residuals with the
exact Jacobian, plus a Tikhonov term: the Gaussian prior of the errors (sizes ``s`` from ``[errors]`` of
the machine.toml) carried onto the base parameters, ``b = p_base + B p_dep`` having prior covariance
``C_b = S_base^2 + B S_dep^2 B^T`` (pseudo-observations ``L^-1 b`` with ``C_b = L L^T``; the maximum
a-posteriori estimate; it only matters for parameters the data barely see). A diagonal ``S_base^2`` alone
would hold a base parameter tighter than the combination it estimates and bias it (hexapod: errors up to
5 sigma). The machine a set of base values stands for is the most plausible one under the same prior
(:func:`spread_map`): each base value spread over the errors it regroups in proportion to their prior
variance, not put on its representative alone. To first order every realisation behaves alike; to second
order a representative alone carries an offset or tilt the real machine spreads over its frames, and the
fit, the reported covariance and the compensation then depend on which representative the base set named
(the predicted nest uncertainty by up to 40 %). Spread, they do not (1 % median, 7 % at most). The base
set's regrouping holds at the nominal machine only: at the identified one the errors it regroups act
slightly apart (a tilt makes a length visible: on the Delta a prior-sized move of a regrouped error
changes the fit by 7-18 noise sigmas at the identified machine, 21-54 at 3x the sizes). So with LM and the
prior, where the base set regroups anything, the estimate is the MAP over every error under the same
(diagonal) prior (:func:`_fit` over every error), and the base set says what it determines: ``x = A p``.
On the Delta at 3x its error sizes the held-out error is then 0.88-1.17x a plain least-squares fit's of all
99 errors (5 seeds; 0.96-1.32x for a fit of the base values alone; ``benchmarks/large_errors_bench.py``). The
reported covariance is that of the base values (realised spread at the identified machine); it equals the
MAP's carried onto them to first order, and keeps the CRLB and a plan's prediction comparable.

**Uncertainty**: ``covariance`` is the posterior covariance ``(J^T J / sigma^2 + C_b^-1)^-1`` of the
base parameters at the solution; ``crlb`` the Cramér-Rao bound ``sqrt(diag(sigma^2 (J^T J)^-1))`` without
the prior (:func:`crlb`); ``weak`` the base parameters whose CRLB exceeds their prior size.

**Compensation** (:func:`compensate_targets`): the commands that put the identified machine's task site on
each target (the model's inverse kinematics with the identified errors).

Units: parameters in mm or deg (the model's :meth:`~pmcal.calib.chain_model.ChainModel.error_units`),
targets mm in the base frame, commands deg / mm.

Example
-------
>>> rng = np.random.default_rng(3)                                       # doctest: +SKIP
>>> cmd = twin.sample_commands(48, rng)
>>> y = twin.measure(cmd, true_errors, rng)
>>> res = identify_chain(twin, cmd, y, twin.sigma_mm)
>>> res.rank, res.chi2_per_dof, res.combinations["arm1.dz"]
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Mapping

import numpy as np
import scipy.linalg
from scipy import stats

from pmcal.calib.chain_model import ChainModel
from pmcal.calib.solvers import METHODS, SOLVERS
from pmcal.calib.solvers.local import lm
from pmcal.calib.solvers.problem import box_problem
from pmcal.calib.solvers.result import IdentResult
from pmcal.threads import blas_policy

#: Share of the largest singular value of the prior-scaled Jacobian below which a direction counts as unseen
#: (structural rank, :func:`base_parameters`).
RANK_TOL = 1e-7
#: a direction above RANK_MARGIN x RANK_TOL of the most visible one is one every campaign must determine
#: (:meth:`BaseSet.clear_rank`): two decades of margin over the tolerance, where CAD models' spectra thin out
RANK_MARGIN = 100.0

#: Folds of the held-out self-check (:func:`held_out_check`): poses ``i % HELD_OUT_FOLDS`` left out in turn.
HELD_OUT_FOLDS = 5
#: The self-check fails when its held-out chi-square exceeds what noise gives with this probability...
HELD_OUT_P = 1e-3
#: ...and the held-out error is more than this factor above what the fit predicts for it (RMS).
HELD_OUT_RATIO = 1.5
#: An identified base value beyond this many prior sigmas is flagged (``beyond_prior``).
PRIOR_SIGMAS = 5.0


@dataclass
class BaseSet:
    """The base-parameter reduction of an identification Jacobian (:func:`base_parameters`).

    keys : every parameter considered.
    base : the identifiable base parameters (pivot order: the best-determined first).
    dependent : the others (not separately identifiable).
    regroup : (len(base), len(dependent)) ``B``: ``J[:, dependent] = J[:, base] @ B`` (parameter units).
    combinations : base key -> the combination its identified value estimates, in words.
    unidentifiable : for each dependent key, the direction the data cannot see, in words.
    rank : number of base parameters.
    condition_number : of the base columns (whitened, prior-scaled, unit-normalised).
    diag_r : |R_ii| of the pivoted QR (whitened, prior-scaled units: noise sigmas per prior size).
    singular_values : of the whitened, prior-scaled Jacobian, largest first: ``rank`` of them are above the
        rank tolerance times the largest (:meth:`clear_rank` counts those well above it).
    """

    keys: list[str]
    base: list[str]
    dependent: list[str]
    regroup: np.ndarray
    combinations: dict[str, str]
    unidentifiable: list[str]
    rank: int
    condition_number: float
    diag_r: np.ndarray
    singular_values: np.ndarray

    def clear_rank(self, share: float = RANK_TOL * RANK_MARGIN) -> int:
        """How many directions are above ``share`` of the most visible one (default :data:`RANK_MARGIN` times
        the rank tolerance): the ones a campaign must determine too. Where a CAD model's directions thin out
        without a gap (gepetto_digit: 3e-7, 2e-7, 1e-7, 8e-8 ... of the largest), the count at the tolerance
        itself differs by one or two between two spreads of poses, and a campaign of random poses was called
        unusable for missing a direction at 1e-7 that no campaign measures."""
        sv = self.singular_values
        if not sv.size or sv[0] <= 0:
            return self.rank
        return min(self.rank, int(np.sum(sv > share * sv[0])))

    def combination_values(self, params: Mapping[str, float]) -> np.ndarray:
        """The values (len(base),) the base parameters estimate on a machine with errors ``params``:
        ``p_base + B p_dependent`` (the true values a fit of the base set should recover)."""
        pb = np.array([params.get(k, 0.0) for k in self.base])
        pd = np.array([params.get(k, 0.0) for k in self.dependent])
        return pb + (self.regroup @ pd if len(pd) else 0.0)


def _by_size(w: np.ndarray) -> np.ndarray:
    """Indices of ``w`` largest first; sizes equal to 9 decimals in index order (not by their last bits)."""
    return np.lexsort((np.arange(len(w)), -np.round(w, 9)))


def _term(coef: float, name: str) -> str:
    sign = "-" if coef < 0 else "+"
    mag = abs(coef)
    return f" {sign} {name}" if abs(mag - 1.0) < 1e-6 else f" {sign} {mag:.4g} {name}"


#: Two remaining lengths closer than this (relative to the larger, and absolute in unit-normalised columns)
#: are a tie, decided by key order: equivalent errors (a frame's offset and its child's) tie exactly, and the
#: last bits of their norms differ between BLAS kernels (OpenBLAS Haswell vs SkylakeX).
TIE_TOL = 1e-9


def _geqp3(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``R`` (min(m, n), n) and the column order ``piv`` of LAPACK's pivoted QR ``A[:, piv] = Q R``
    (``geqp3``, what ``scipy.linalg.qr(A, mode="r", pivoting=True)`` calls, without its ~50 us of Python
    around a call that takes 3 us on the small Jacobians of a campaign)."""
    qr, piv, _, _, info = scipy.linalg.lapack.dgeqp3(np.asfortranarray(A, dtype=float))
    if info < 0:
        raise ValueError(f"geqp3: illegal argument {-info}")
    return np.triu(qr[: min(A.shape)]), piv - 1


def _ties_to_first(R: np.ndarray, piv: np.ndarray, rank: int) -> bool:
    """Whether each of the first ``rank`` pivots of a pivoted QR (``R``, ``piv``) is the canonical one: of the
    columns whose remaining length ``||R[i:, j]||`` is the largest within :data:`TIE_TOL`, the lowest index."""
    n = R.shape[1]
    tail = np.sqrt(np.cumsum((R * R)[::-1], axis=0)[::-1])[:rank]       # tail[i, j] = ||R[i:, j]||
    later = np.arange(n)[None, :] >= np.arange(rank)[:, None]
    norms = np.where(later, tail, -np.inf)
    best = norms.max(axis=1, initial=-np.inf)
    tied = norms >= best[:, None] - TIE_TOL * (1.0 + best[:, None])
    return bool(np.all(np.argmin(np.where(tied, piv[None, :], n), axis=1) == np.arange(rank)))


def _gram_schmidt_pivots(A: np.ndarray, stop: float, count: int | None = None) -> np.ndarray:
    """The pivot order of ``A``'s columns by Gram-Schmidt with column pivoting: repeatedly the column that
    keeps the most of its length beyond the ones taken, ties within :data:`TIE_TOL` to the lowest index,
    while it keeps more than ``stop`` (and at most ``count`` columns); the columns not taken follow in index
    order. (Modified Gram-Schmidt, each new direction removed twice: the lengths compared are accurate to
    ~1e-15.)"""
    V = np.array(A, float)
    rest = list(range(A.shape[1]))
    taken: list[int] = []
    most = A.shape[0] if count is None else min(int(count), A.shape[0])
    while rest and len(taken) < most:
        norms = np.linalg.norm(V[:, rest], axis=0)
        best = norms.max()
        if best <= stop:
            break
        k = int(np.flatnonzero(norms >= best - TIE_TOL * (1.0 + best))[0])      # rest is in index order
        j = rest.pop(k)
        q = V[:, j] / norms[k]
        taken.append(j)
        for _ in range(2):
            V[:, rest] -= np.outer(q, q @ V[:, rest])
    return np.r_[np.asarray(taken, int), np.asarray(rest, int)]


def _rank(A: np.ndarray, rank_tol: float) -> tuple[int, np.ndarray]:
    """The numerical rank of ``A`` (its singular values above ``rank_tol`` times the largest) and the singular
    values. They do not depend on the column order, so neither does the rank (the count of ``|R_ii|`` above a
    tolerance does)."""
    sv = scipy.linalg.svdvals(A) if A.size else np.zeros(0)
    return (int(np.sum(sv > rank_tol * sv[0])) if sv.size and sv[0] > 0 else 0), sv


def _pivoted_qr_r(A: np.ndarray, rank: int) -> tuple[np.ndarray, np.ndarray]:
    """``R`` (min(m, n), n) and the column order ``piv`` (``A[:, piv] = Q R``) of a QR with column pivoting
    whose first ``rank`` pivots break every tie between columns of equal remaining length (:data:`TIE_TOL`) to
    the lowest index. LAPACK's ``geqp3`` breaks such ties by the last bits of the norms, which differ between
    BLAS kernels: its result is kept where it broke none among the first ``rank`` pivots (no equivalent
    errors), else those pivots come from :func:`_gram_schmidt_pivots` and the columns are factored in that
    order. Where every column is a base one, the order is the columns' own (nothing to decide)."""
    R, piv = _geqp3(A)
    if rank == A.shape[1]:                     # every column a base one: key order, no tie to decide
        return R, np.sort(piv)                 # (R's columns stay in pivot order: only its singular values
                                               # are used, the same in any column order)
    if _ties_to_first(R, piv, rank):
        return R, piv
    C = R[:, np.argsort(piv)]                   # A = Q C: same lengths and angles, min(m, n) rows only
    piv = _gram_schmidt_pivots(C, 0.0, rank)
    return np.linalg.qr(C[:, piv], mode="r"), piv


@blas_policy()
def base_parameters(J: np.ndarray, keys: list[str], scale: np.ndarray | None = None,
                    rank_tol: float = RANK_TOL) -> BaseSet:
    """Base-parameter reduction of a Jacobian by QR with column pivoting, ties to key order (module docstring).

    Parameters
    ----------
    J : (m, P) whitened Jacobian (residual units: noise sigmas) per parameter unit.
    keys : the P parameter names.
    scale : (P,) typical size of each parameter (its prior), so columns of mixed units compare; default 1.
    rank_tol : the rank is the number of singular values of the scaled Jacobian ``J * scale`` above
        ``rank_tol`` times the largest (directions along which errors of their typical size move the readings
        by more than that share of what the most visible direction does); a column whose whole effect is
        below that share is an error with no effect. The pivots that name the base parameters are chosen
        on column-normalised columns.

    Example
    -------
    >>> J = np.array([[1.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 1.0, 1.0]])
    >>> b = base_parameters(J, ["a", "b", "c"])
    >>> b.rank, b.combinations[b.base[0]] in ("a + b", "b + a")
    (2, True)
    """
    J = np.asarray(J, float)
    P = J.shape[1]
    scale = np.ones(P) if scale is None else np.asarray(scale, float)
    Js = J * scale
    norms = np.linalg.norm(Js, axis=0)
    zero = norms <= rank_tol * max(float(norms.max(initial=0.0)), 1e-300)   # no effect the rank can count
    Jn = Js / np.where(zero, 1.0, norms)
    r, sv_all = _rank(np.where(zero, 0.0, Js), rank_tol)
    R, piv = _pivoted_qr_r(np.where(zero, 0.0, Jn), r)
    d = np.abs(np.diag(R))
    dep_order = np.argsort(piv[r:], kind="stable")          # the dependent ones in key order, not LAPACK's
    base_idx, dep_idx = piv[:r], piv[r:][dep_order]
    beta = scipy.linalg.solve_triangular(R[:r, :r], R[:r, r:][:, dep_order]) if r and len(dep_idx) \
        else np.zeros((r, len(dep_idx)))
    # Back to parameter units: Jn_dep = Jn_base beta  ->  J_dep = J_base B,  B_ij = beta_ij (n_j / s_j) (s_i / n_i)
    nb = np.where(zero, 1.0, norms)
    B = beta * (scale[base_idx] / nb[base_idx])[:, None] * (nb[dep_idx] / scale[dep_idx])[None, :]
    B[:, zero[dep_idx]] = 0.0
    base = [keys[i] for i in base_idx]
    dep = [keys[i] for i in dep_idx]
    combos = {k: k for k in base}
    for i, k in enumerate(base if dep else ()):                # a base parameter regroups dependent ones
        # relative size of each term in prior units: skip negligible ones
        w = np.abs(B[i]) * scale[dep_idx] / scale[base_idx[i]]
        order = _by_size(w)
        combos[k] = k + "".join(_term(B[i, j], dep[j]) for j in order if w[j] > 1e-6)
    unid = []
    for j, k in enumerate(dep):
        if zero[dep_idx[j]]:
            unid.append(f"{k} (no effect on the targets)")
            continue
        w = np.abs(B[:, j]) * scale[base_idx] / scale[dep_idx[j]]
        order = _by_size(w)
        terms = "".join(_term(-B[i, j], base[i]) for i in order if w[i] > 1e-6)
        unid.append(f"{k}{terms} (seen only through the base parameters)")
    sv = np.linalg.svd(R[:r, :r], compute_uv=False) if r else np.zeros(0)     # = Jn[:, base]'s (Q orthonormal)
    cond = float(sv[0] / sv[-1]) if r and sv[-1] > 0 else np.inf
    return BaseSet(keys=list(keys), base=base, dependent=dep, regroup=B, combinations=combos,
                   unidentifiable=unid, rank=r, condition_number=cond, diag_r=d, singular_values=sv_all)


@dataclass
class ChainIdentResult:
    """Outcome of :func:`identify_chain` (cf. ``scipy.optimize.OptimizeResult``).

    Attributes
    ----------
    params : every considered key -> identified value (mm / deg): the identified machine, the most plausible
        under the prior whose base combinations are ``x`` (each base value spread over the errors it
        regroups in proportion to their prior variance, :func:`spread_map`; errors without effect 0). Pass
        it to the model to predict or compensate.
    base : the identified base parameters, in the order of ``x``, ``covariance``, ``std``.
    units : unit of each base parameter (``"mm"`` / ``"deg"``).
    x : (len(base),) identified values.
    covariance : posterior covariance of ``x`` (data and Tikhonov prior), unit^2.
    std : base key -> sqrt of the covariance diagonal.
    crlb : base key -> Cramér-Rao standard deviation from the data alone (no prior); inf if not determined.
    combinations : base key -> the combination of errors its value estimates, in words.
    unidentifiable : the directions the data cannot see, in words (one per dependent parameter).
    weak : base keys whose CRLB exceeds their prior size (the prior, not the data, sets them).
    rank, condition_number : of the base Jacobian (whitened, prior-scaled, column-normalised).
    chi2, dof, chi2_per_dof : whitened residual sum of squares at the solution, its degrees of freedom
        (target coordinates minus effective parameters), their ratio (about 1 when the model fits to noise).
    residual_rms_mm : RMS target (or reading) residual, mm (not whitened).
    sigma_mm : the tracker noise used, mm.
    n_poses : poses used (finite commands and targets).
    success, message, nfev, wall_time : from the solver.
    basis : the :class:`BaseSet` (regrouping matrix included).
    solver : the underlying :class:`pmcal.calib.solvers.result.IdentResult`.
    realization : (len(params), len(base)) ``M``: the machine ``params = M x`` (:meth:`base_derivative`).
    error_covariance : (len(params), len(params)) posterior covariance of every error considered (data and
        the prior), unit^2, where the fit has a prior (else None): what :meth:`predicted_task_std` propagates,
        so that errors the data cannot see, or see only in combination, count with what the prior knows of
        them.
    """

    params: dict[str, float]
    base: list[str]
    units: list[str]
    x: np.ndarray
    covariance: np.ndarray
    std: dict[str, float]
    crlb: dict[str, float]
    combinations: dict[str, str]
    unidentifiable: list[str]
    weak: list[str]
    rank: int
    condition_number: float
    chi2: float
    dof: float
    chi2_per_dof: float
    residual_rms_mm: float
    sigma_mm: float
    n_poses: int
    success: bool
    message: str
    nfev: int
    wall_time: float
    basis: BaseSet
    solver: IdentResult | None = None
    info: dict = field(default_factory=dict)
    realization: np.ndarray | None = None
    error_covariance: np.ndarray | None = None

    def predicted_task_std(self, J: np.ndarray) -> np.ndarray:
        """1-sigma (n, C) of the task coordinates a compensation with the identified errors leaves, from
        their derivatives ``J`` (n, C, len(params)) by every error (in the order of ``params``; e.g. the
        twin's ``task_jacobian`` at the compensated commands), in the coordinates' units. With a prior, the
        posterior over every error (:attr:`error_covariance`): an error that moves the task point but no
        tracker reading (a task site on a body no nest sits on) counts with its prior size, as it stays
        uncorrected. Without a prior, the base values' covariance."""
        if self.error_covariance is not None:
            return np.sqrt(np.einsum("ncp,pq,ncq->nc", J, self.error_covariance, J))
        Jb = self.base_derivative(J)
        return np.sqrt(np.einsum("ncp,pq,ncq->nc", Jb, self.covariance, Jb))

    def predicted_task_law(self, J: np.ndarray, columns=None) -> np.ndarray:
        """How the compensated task error's RMS over ``n`` targets spreads from one campaign to the next, from
        the derivatives ``J`` (n, C, len(params)) as in :meth:`predicted_task_std`, over the task coordinates
        ``columns`` (indices; all when None).

        Over campaigns the mean square error is ``sum_i w_i z_i^2``, ``z_i`` independent standard normal: one
        term per direction of the posterior the targets see, ``w_i`` the eigenvalues of ``A P`` (``A`` the
        targets' mean ``J^T J``, ``P`` the posterior covariance). Their sum is the square of what
        :meth:`predicted_task_std` gives as RMS; ``sum(w)^2 / sum(w^2)`` counts the directions that carry it.
        One direction: a campaign ends above 1.5x the prediction with probability 13 %, however good the
        identification; many: the prediction holds campaign by campaign. :func:`rms_band` and
        :func:`share_above` read the law.

        Returns the weights ``w`` (largest first; the coordinates' units squared)."""
        J = np.asarray(J, float)
        if columns is not None:
            J = J[:, list(columns), :]
        if self.error_covariance is not None:
            P = self.error_covariance
        else:
            J, P = self.base_derivative(J), self.covariance
        A = np.einsum("ncp,ncq->pq", J, J) / max(J.shape[0], 1)
        lam, V = np.linalg.eigh((P + P.T) / 2.0)
        root = (V * np.sqrt(np.clip(lam, 0.0, None))) @ V.T
        w = np.linalg.eigvalsh(root @ A @ root)[::-1]
        return np.clip(w, 0.0, None)

    def base_derivative(self, J: np.ndarray) -> np.ndarray:
        """Derivatives (..., len(base)) by the identified base values from derivatives (..., len(params)) by
        every error considered (in the order of ``params``) at the identified machine: ``J M``
        (:func:`spread_map`; the identity on the base columns where the base set regroups nothing)."""
        return J @ self.realization

    def summary(self) -> dict:
        """JSON-friendly digest (parameters, uncertainties, identifiability, fit quality)."""
        return {"params": self.params, "base": self.base, "units": self.units,
                "std": self.std, "crlb": self.crlb, "combinations": self.combinations,
                "unidentifiable": self.unidentifiable, "weak": self.weak, "rank": self.rank,
                "condition_number": self.condition_number, "chi2_per_dof": self.chi2_per_dof,
                "residual_rms_mm": self.residual_rms_mm, "sigma_mm": self.sigma_mm, "n_poses": self.n_poses,
                "success": self.success, "message": self.message}


def prior_set_directions(info: np.ndarray, prior_cov: np.ndarray, n_poses: int) -> dict:
    """The directions of the base set that the prior, not the data, determines: ``{"count", "poses_needed"}``.

    The data's information ``info`` (base units^-2) whitened by the prior covariance ``prior_cov``
    (``L^T info L``, ``prior_cov = L L^T``) has an eigenvalue below 1 along each direction the campaign's
    ``n_poses`` poses know less of than the prior does (a base parameter's CRLB above its prior size reads
    the same, but one such direction makes every base parameter with a part in it look so). More poses of the
    same kind add information in proportion: ``poses_needed`` is how many bring the weakest to 1
    (``n_poses / lambda_min``; inf when the data do not see it at all), 0 when none is below 1.

    >>> prior_set_directions(np.diag([4.0, 0.5]), np.eye(2), 48)
    {'count': 1, 'poses_needed': 96}
    """
    L = np.linalg.cholesky(prior_cov)
    lam = np.linalg.eigvalsh(L.T @ info @ L)
    low = lam[lam < 1.0]
    if not low.size:
        return {"count": 0, "poses_needed": 0}
    weakest = float(low.min())
    need = int(np.ceil(n_poses / weakest)) if weakest > n_poses / 1e12 else float("inf")
    return {"count": int(low.size), "poses_needed": need}


def base_prior_cov(model: ChainModel, basis: BaseSet) -> np.ndarray:
    """Prior covariance (len(base), len(base)) of the base parameters, their units squared. A base parameter
    estimates the combination ``b = p_base + B p_dep``, so ``cov_b = S_base^2 + B S_dep^2 B^T`` with ``S`` the
    errors' prior sizes (``model.prior_std``): correlated where two base parameters regroup the same error."""
    cov = np.diag(model.prior_std(basis.base) ** 2)
    if basis.dependent:
        cov += (basis.regroup * model.prior_std(basis.dependent) ** 2) @ basis.regroup.T
    return cov


def combination_matrix(basis: BaseSet) -> np.ndarray:
    """(len(base), len(keys)) ``A``: the base values ``b = A p`` a machine with errors ``p`` (in the order of
    ``basis.keys``) has, ``A = [I B]`` in base and dependent columns."""
    keys = list(basis.keys)
    A = np.zeros((len(basis.base), len(keys)))
    A[:, [keys.index(k) for k in basis.base]] = np.eye(len(basis.base))
    if basis.dependent:
        A[:, [keys.index(k) for k in basis.dependent]] = basis.regroup
    return A


def spread_map(model: ChainModel, basis: BaseSet) -> np.ndarray:
    """(len(keys), len(base)) ``M``: the errors ``p = M b`` of the most plausible machine under the prior
    whose base combinations are ``b`` (``b = A p``, :func:`combination_matrix`; ``M = S^2 A^T (A S^2 A^T)^-1``,
    ``S`` the errors' prior sizes). Each base value is spread over the errors it regroups in proportion to
    their prior variance, instead of being put on its representative alone: the same machine whichever
    representative the base set names (to first order they all behave alike; to second order a
    representative alone carries a tilt or offset the real machine spreads over its frames), with the same
    base values. Errors with no effect get 0."""
    A = combination_matrix(basis)
    if not basis.dependent:                    # nothing regrouped: the base values are the errors
        return A.T
    S2 = model.prior_std(list(basis.keys)) ** 2
    return (S2[:, None] * A.T) @ _spd_inverse((A * S2) @ A.T)


def _valid(commands: np.ndarray, targets: np.ndarray) -> np.ndarray:
    return np.isfinite(commands).all(axis=1) & np.isfinite(targets).all(axis=(1, 2))


def flat_jacobian(model: ChainModel, commands, params, keys) -> np.ndarray:
    """Jacobian (N*K*3, len(keys)) of the nests' coordinates (mm, poses then nests then x, y, z) with
    respect to ``keys`` (per key unit) at commands (N, M) on the machine with errors ``params``."""
    J = model.jacobian(commands, params, keys)
    return J.reshape(-1, len(keys))


def reading_operator(n_poses: int, reference: str = "previous", segments=None) -> np.ndarray:
    """(rows, n_poses) matrix turning per-pose distances into the readings of a scale relative to a
    reference pose: ``"previous"`` gives ``d_{k+1} - d_k``, ``"first"`` gives ``d_k - d_first`` (k after the
    first), within each chain of poses (``segments``: one label per pose, a new chain where it changes;
    None: one chain). Rows follow the poses' order.

    >>> reading_operator(3)
    array([[-1.,  1.,  0.],
           [ 0., -1.,  1.]])
    """
    if reference not in ("previous", "first"):
        raise ValueError(f"unknown reading reference {reference!r} (previous or first)")
    seg = np.zeros(n_poses, int) if segments is None else np.asarray(segments)
    if len(seg) != n_poses:
        raise ValueError(f"{len(seg)} chain labels for {n_poses} poses")
    start = np.concatenate(([n_poses > 0], seg[1:] != seg[:-1]))[:n_poses]     # a chain begins here
    rows = np.flatnonzero(~start)
    if reference == "previous":
        ref = rows - 1
    else:
        ref = np.maximum.accumulate(np.where(start, np.arange(n_poses), 0))[rows]
    D = np.zeros((rows.size, n_poses))
    D[np.arange(rows.size), rows] = 1.0
    D[np.arange(rows.size), ref] = -1.0
    return D


class _Observations:
    """What identification fits: the measured values ``y`` (flat, mm) and the model's prediction and exact
    Jacobian of them at the campaign's commands. Tracker nests (``model.targets``, N x K x 3) or, for a
    model whose ``reading_reference`` is set (``measure = "distance"``), scale readings: ``D`` times the
    distances of :meth:`observe` (:func:`reading_operator`)."""

    def __init__(self, model: ChainModel, commands: np.ndarray, measured, segments=None, covariance=None,
                 sigma: float = 1.0):
        self.model = model
        self.reference = model.reading_reference
        measured = np.asarray(measured, float)
        if self.reference is None:
            if measured.ndim != 3 or measured.shape[0] != commands.shape[0] or measured.shape[2] != 3:
                raise ValueError(f"targets must be (N, K, 3) with N = {commands.shape[0]} poses, got "
                                 f"{measured.shape}")
            ok = _valid(commands, measured)
            self.commands, self.y = commands[ok], measured[ok].reshape(-1)
            self.D = None
        else:
            D = reading_operator(len(commands), self.reference, segments)
            if measured.shape != (D.shape[0],):
                raise ValueError(f"{measured.size} readings for {D.shape[0]} pose pairs of {len(commands)} poses")
            if not np.isfinite(commands).all():
                raise ValueError("a reading campaign needs every pose's commands")
            ok = np.isfinite(measured)
            self.commands, self.y, self.D = commands, measured[ok], D[ok]
        self.n_poses = len(self.commands)
        # correlated noise (covariance C of the measured values): W = sigma L^-1 (C = L L^T) turns residuals
        # into independent ones of size sigma, so the rest of the fit reads as with white noise
        self.W = None
        if covariance is not None:
            C = np.asarray(covariance, float)
            if C.shape != (len(measured.reshape(-1)),) * 2:
                raise ValueError(f"covariance must be ({measured.size}, {measured.size}), got {C.shape}")
            keep = np.isfinite(measured.reshape(-1)) if self.D is not None else \
                np.repeat(ok, measured.shape[1] * 3)
            C = C if keep.all() else C[np.ix_(keep, keep)]
            self._L = np.linalg.cholesky(C)
            self._sigma = sigma
            self.W = sigma * np.linalg.inv(self._L)
            self.y = self.W @ self.y

    def row_poses(self) -> np.ndarray:
        """(rows,) the pose (or, for readings, the reading) each fitted row belongs to: the held-out check's
        folds keep a pose's coordinates together."""
        if self.D is None:
            return np.repeat(np.arange(self.n_poses), self.y.size // max(self.n_poses, 1))
        return np.arange(self.y.size)

    def residual_mm(self, whitened: np.ndarray) -> np.ndarray:
        """The residuals in mm (not whitened), given the whitened ones of the fit (``W^-1 r = L r / sigma``)."""
        return whitened if self.W is None else self._L @ whitened / self._sigma

    def _white(self, v: np.ndarray) -> np.ndarray:
        return v if self.W is None else self.W @ v

    def predict(self, params) -> np.ndarray:
        if self.D is None:
            return self._white(self.model.targets(self.commands, params).reshape(-1))
        return self._white(self.D @ self.model.observe(self.commands, params)[:, 0])

    def jacobian(self, params, keys) -> np.ndarray:
        if self.D is None:
            return self._white(flat_jacobian(self.model, self.commands, params, keys))
        return self._white(self.D @ self.model.observation_jacobian(self.commands, params, keys)[:, 0, :])


#: draws of the campaign-to-campaign law (:func:`rms_band`, :func:`share_above`): quantiles to about 0.5 %
LAW_DRAWS = 100_000


def _law_draws(weights) -> np.ndarray:
    """Mean square errors of :data:`LAW_DRAWS` campaigns under the law of ``weights``
    (:meth:`ChainIdentResult.predicted_task_law`), from a fixed seed: the same law gives the same figures."""
    w = np.asarray(weights, float)
    w = w[w > 1e-12 * max(float(w.sum()), 1e-300)]
    if w.size == 0:
        return np.zeros(LAW_DRAWS)
    rng = np.random.default_rng(0)
    return np.concatenate([rng.chisquare(1.0, size=(10_000, w.size)) @ w for _ in range(LAW_DRAWS // 10_000)])


def law_directions(weights) -> float:
    """How many independent error directions carry a prediction: ``sum(w)^2 / sum(w^2)`` of the law's weights
    (1 when one direction carries it all; 0 when nothing is predicted)."""
    w = np.asarray(weights, float)
    square_sum = float(np.sum(w ** 2))
    return float(w.sum() ** 2 / square_sum) if square_sum > 0 else 0.0


def rms_band(weights, level: float = 0.9) -> tuple[float, float]:
    """The central ``level`` band (low, high) of a campaign's RMS error under the law of ``weights``
    (:meth:`ChainIdentResult.predicted_task_law`), in the error's units.

    Examples
    --------
    >>> lo, hi = rms_band([1.0])            # one direction carries the error: chi-square(1), a wide band
    >>> round(lo, 2), round(hi, 2)
    (0.06, 1.96)
    """
    tail = (1.0 - level) / 2.0
    lo, hi = np.quantile(_law_draws(weights), [tail, 1.0 - tail])
    return float(np.sqrt(lo)), float(np.sqrt(hi))


def share_above(ratio: float, weights) -> float:
    """Probability that a campaign's RMS error exceeds ``ratio`` times the predicted RMS (``sqrt(sum(w))``)
    under the law of ``weights`` (:meth:`ChainIdentResult.predicted_task_law`): 13.4 % at 1.5x for one
    direction.

    Examples
    --------
    >>> round(share_above(1.5, [1.0]), 2)
    0.13
    """
    draws = _law_draws(weights)
    return float(np.mean(draws > ratio ** 2 * float(np.sum(weights))))


#: :func:`held_out_check`'s answer where it cannot judge (too few poses, a direction left free, no prior)
NOT_CHECKED = {"folds": 0, "passed": None, "rms_mm": None, "predicted_rms_mm": None, "chi2_per_dof": None,
               "p_value": None}


def held_out_check(J: np.ndarray, r: np.ndarray, groups: np.ndarray, prior_precision: np.ndarray | float,
                   sigma: float, folds: int = HELD_OUT_FOLDS) -> dict:
    """Does the fit predict what it did not see? Linearised k-fold cross-validation at the solution.

    Each fold (the rows of poses ``i % folds``) is left out in turn: the fit without it is one Gauss-Newton
    step from the solution, ``x' = x - H_f^-1 J_f^T r_f`` (``H_f`` the information of the other rows plus the
    prior), and its residual on the fold is ``r_f + J_f H_f^-1 J_f^T r_f``. If the model is right these are
    noise plus the prediction's own error, covariance ``I + J_f H_f^-1 J_f^T`` (whitened), so their
    Mahalanobis sum over all folds is chi-square with as many degrees of freedom as rows. A model that
    fits its campaign to the noise with knobs that mean nothing (chi2/dof 1 in sample) fails here.

    Parameters
    ----------
    J : (n, p) whitened Jacobian of the residuals by the base parameters at the solution.
    r : (n,) whitened residuals at the solution (measured minus predicted, noise sigmas).
    groups : (n,) pose index of each row (folds are made of whole poses).
    prior_precision : (p, p) inverse prior covariance of the base parameters (0: no prior).
    sigma : noise, mm (to state the errors in mm).
    folds : number of folds (fewer when there are fewer poses; none below 2 poses per fold).

    Returns
    -------
    dict
        ``rms_mm`` the held-out residual RMS (mm), ``predicted_rms_mm`` what noise and the fit's own
        uncertainty predict for it, ``chi2_per_dof`` of the held-out residuals, ``p_value``, ``folds``, and
        ``passed`` (False when the chi-square is beyond :data:`HELD_OUT_P` and the RMS more than
        :data:`HELD_OUT_RATIO` above its prediction); ``folds`` 0 and ``passed`` None when too few poses,
        or when a fold left out leaves a direction undetermined (no prior, as few poses as parameters).
    """
    poses = np.unique(groups)
    k = min(folds, len(poses) // 2)
    if k < 2:
        return dict(NOT_CHECKED)
    fold_of = {p: i % k for i, p in enumerate(poses)}
    fold = np.array([fold_of[g] for g in groups])
    H = J.T @ J + prior_precision
    chi2, sq, var, n = 0.0, 0.0, 0.0, 0
    for f in range(k):
        rows = fold == f
        Jf, rf = J[rows], r[rows]
        try:                                 # without the fold (and the prior) a direction may be left free
            L = np.linalg.cholesky(H - Jf.T @ Jf)
        except np.linalg.LinAlgError:
            return dict(NOT_CHECKED)
        W = scipy.linalg.solve_triangular(L, Jf.T, lower=True)
        G = W.T @ W                                                  # J_f H_f^-1 J_f^T
        held = rf + G @ rf
        C = np.eye(len(rf)) + G
        chi2 += float(held @ np.linalg.solve(C, held))
        sq += float(held @ held)
        var += float(np.trace(C))
        n += len(rf)
    rms, predicted = sigma * np.sqrt(sq / n), sigma * np.sqrt(var / n)
    p = float(stats.chi2.sf(chi2, n))
    return {"folds": k, "rms_mm": float(rms), "predicted_rms_mm": float(predicted), "chi2_per_dof": chi2 / n,
            "p_value": p,
            "passed": bool(np.isfinite(chi2)) and not (p < HELD_OUT_P and rms > HELD_OUT_RATIO * predicted)}


def _spd_inverse(M: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric positive-definite matrix by its Cholesky factor; the pseudo-inverse when it is
    not numerically positive definite (a direction the data and the prior leave free)."""
    try:
        Li = np.linalg.inv(np.linalg.cholesky(M))
    except np.linalg.LinAlgError:
        return np.linalg.pinv(M)
    return Li.T @ Li


@blas_policy()
def identify_chain(model: ChainModel, commands, targets, sigma_mm: float | None = None,
                   keys: list[str] | None = None, *, prior: bool = True, rank_tol: float = RANK_TOL,
                   max_nfev: int | None = 100, method: str = "lm", seed: int | None = None,
                   segments=None, covariance=None, basis: BaseSet | None = None, **options) -> ChainIdentResult:
    """Identify the geometric errors of a closed-chain machine from tracker measurements.

    Parameters
    ----------
    model : the machine (:class:`~pmcal.calib.chain_model.ChainModel`).
    commands : (N, M) motor commands of the campaign, deg / mm.
    targets : (N, K, 3) measured nest positions, mm, base frame; for a model measuring a distance (its
        ``reading_reference`` set: ``measure = "distance"``) the scale readings (rows,) mm, one per row of
        :func:`reading_operator` (NaN: a reading missing).
    sigma_mm : tracker noise (1 sigma per coordinate or reading), mm; default the model's ``sigma_mm``.
    keys : the errors to consider (default every ``model.error_keys``); reduced to the base set.
    prior : add the Tikhonov prior (module docstring); False: plain LM on the base set.
    rank_tol : relative QR threshold of the base-set reduction (:func:`base_parameters`).
    max_nfev : LM evaluation limit.
    method : ``"lm"`` (default) or another method of :data:`pmcal.calib.solvers.METHODS` (``"hga"``, the
        paper's hybrid GA; ``"tikhonov"`` with the L-curve; ``"tsvd"``; ...) run on the same base-set
        problem (with the prior unless ``prior=False``); ``seed`` and ``options`` go to it. The global
        methods evaluate a population of machines per generation: slow on a whole chain.
    segments : for readings: a chain label per pose (a new chain of readings where it changes); None: one.
    covariance : (n, n) covariance (mm^2) of the measured values (the flattened targets or the readings),
        for correlated noise, e.g. :func:`reading_covariance` (motor motion errors enter adjacent readings);
        the fit is then generalised least squares. None: independent noise of ``sigma_mm``.
    basis : the base set to identify (e.g. the machine's :func:`structural_basis`, the same for every
        campaign, so that two identifications estimate the same combinations); None: the campaign's own
        (pivoted QR of its Jacobian). Used only where the campaign determines as many combinations as it has
        (else the campaign's own, ``info["basis"]`` says which).

    Runs under pmcal's BLAS thread policy (:func:`pmcal.threads.blas_policy`: one thread unless
    ``PMCAL_BLAS_THREADS`` says otherwise; threads spinning on these small matrices cost 10-100x).

    Returns
    -------
    ChainIdentResult

    Raises
    ------
    ValueError
        Shapes that do not match the model, or fewer valid poses than base parameters.
    """
    if method not in METHODS:
        raise ValueError(f"unknown identification method {method!r} (known: {', '.join(METHODS)})")
    t0 = time.perf_counter()
    commands = np.atleast_2d(np.asarray(commands, float))
    sigma = float(model.sigma_mm if sigma_mm is None else sigma_mm)
    if not (np.isfinite(sigma) and sigma > 0):
        raise ValueError(f"sigma_mm must be positive, got {sigma_mm}")
    obs = _Observations(model, commands, targets, segments, covariance, sigma)
    commands = obs.commands
    keys = list(keys or (basis.keys if basis is not None else model.error_keys))
    if basis is not None and list(basis.keys) != keys:
        raise ValueError("the basis is a base set of other errors than keys")
    scale = model.prior_std(keys)
    J0 = obs.jacobian(None, keys)
    if not np.isfinite(J0).all():
        bad = np.flatnonzero(~np.isfinite(model.observe(commands) if obs.D is not None else
                                          J0.reshape(len(commands), -1)).all(axis=1))
        raise ValueError(f"the nominal machine cannot assemble {len(bad)} measured pose(s) (rows "
                         f"{', '.join(str(i + 1) for i in bad[:5])}): are they inside the workspace?")
    own = base_parameters(J0 / sigma, keys, scale, rank_tol)
    which = "given" if basis is not None and own.rank == basis.rank else "campaign"
    basis = basis if which == "given" else own
    base = basis.base
    units = model.error_units(base)
    prior_cov = base_prior_cov(model, basis)
    sb = np.sqrt(np.diag(prior_cov))
    y = obs.y
    if y.size < len(base):
        raise ValueError(f"{len(commands)} poses give {y.size} coordinates for {len(base)} base parameters")

    M = spread_map(model, basis)
    if prior and method == "lm" and basis.dependent:
        # the MAP over every error under the same (diagonal) prior: the base set's regrouping holds at the
        # nominal machine only, and at the identified one the regrouped errors act slightly apart (a tilt makes
        # a length visible); the base set then says what the fit determines (module docstring)
        p, sol, Jp = _fit(model, obs, keys, keys, np.eye(len(keys)), J0, sigma,
                          np.diag(model.prior_std(keys) ** 2), True, max_nfev=max_nfev)
        x = combination_matrix(basis) @ p
    else:
        x, sol, Jp = _fit(model, obs, keys, base, M, J0, sigma, prior_cov, prior, method, max_nfev, seed, options)
        p = M @ x
    Jf = Jp / sigma
    Jb = Jf @ M
    # the solver's residuals at its solution (data first, then any prior pseudo-observations)
    resid = sol.residuals[:y.size] if len(sol.residuals) >= y.size else y - obs.predict(dict(zip(keys, map(float, p))))
    info_data = Jb.T @ Jb            # by the base values, realised spread at the identified machine
    cov = _spd_inverse(info_data + (np.linalg.inv(prior_cov) if prior else 0.0))
    p_eff = float(np.trace(cov @ info_data))
    fisher = _spd_inverse(info_data) if prior else cov
    crlb_std = np.sqrt(np.clip(np.diag(fisher), 0.0, None))
    weak_dirs = prior_set_directions(info_data, prior_cov, int(len(commands)))
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    chi2 = float(np.sum((resid / sigma) ** 2))
    dof = max(y.size - p_eff, 1.0)
    params = dict(zip(keys, map(float, p)))
    error_cov = _spd_inverse(Jf.T @ Jf + np.diag(1.0 / model.prior_std(keys) ** 2)) if prior else None
    # without a prior a fold left out often leaves a direction free (as many readings as parameters): not run
    held_out = held_out_check(Jb, resid / sigma, obs.row_poses(), np.linalg.inv(prior_cov), sigma) if prior \
        else dict(NOT_CHECKED)
    return ChainIdentResult(
        params=params, base=list(base), units=units, x=x, covariance=cov, std=dict(zip(base, map(float, std))),
        crlb=dict(zip(base, map(float, crlb_std))), combinations=basis.combinations,
        unidentifiable=basis.unidentifiable, weak=[k for k, c, s in zip(base, crlb_std, sb) if c > s],
        rank=basis.rank, condition_number=basis.condition_number, chi2=chi2, dof=dof, chi2_per_dof=chi2 / dof,
        residual_rms_mm=float(np.sqrt(np.mean(obs.residual_mm(resid) ** 2))), sigma_mm=sigma, n_poses=int(len(commands)),
        success=bool(sol.success), message=str(sol.message), nfev=int(sol.n_eval),
        wall_time=time.perf_counter() - t0, basis=basis, solver=sol, realization=M, error_covariance=error_cov,
        info={"effective_parameters": p_eff, "prior_std": dict(zip(base, map(float, sb))),
              "prior_covariance": prior_cov, "basis": which, "held_out": held_out, "prior_set": weak_dirs,
              "beyond_prior": [k for k, v, s in zip(base, x, sb) if abs(v) > PRIOR_SIGMAS * s]})


def _fit(model: ChainModel, obs: "_Observations", keys: list[str], names: list[str], M: np.ndarray,
         J0: np.ndarray, sigma: float, prior_cov: np.ndarray, prior: bool, method: str = "lm",
         max_nfev: int | None = None, seed: int | None = None, options: dict | None = None):
    """Fit the values ``x`` of ``names`` whose machine is the errors ``M x`` (in the order of ``keys``) by
    ``method``, from the nominal machine (whose Jacobian over ``keys`` is ``J0``); with the prior ``prior_cov``
    of ``x`` when ``prior`` (its sizes also scale the search box). Returns ``x``, the solver's result and every
    key's (unwhitened) Jacobian at the solution (mm per key unit). The base values: ``names`` the base set,
    ``M`` its :func:`spread_map`; the MAP over every error: ``names = keys``, ``M`` the identity."""
    last = {np.zeros(len(names)).tobytes(): J0}           # every key's Jacobian at the last point asked

    def params_of(x: np.ndarray) -> dict[str, float]:
        return dict(zip(keys, map(float, M @ x)))

    def fun(X: np.ndarray) -> np.ndarray:
        return np.stack([obs.y - obs.predict(params_of(x)) for x in X])

    def jacobian(x: np.ndarray) -> np.ndarray:
        key = np.asarray(x, float).tobytes()
        if key not in last:
            last.clear()
            last[key] = obs.jacobian(params_of(x), keys)
        return last[key]

    sb = np.sqrt(np.diag(prior_cov))
    problem = box_problem(fun, names, model.error_units(names), half_width=50.0 * sb, sigma=sigma,
                          jac=lambda x: -jacobian(x) @ M, scale=sb, info={"residual_unit": "mm"})
    work = problem.with_prior(cov=prior_cov) if prior else problem
    sol = lm(work, max_nfev=max_nfev) if method == "lm" else SOLVERS[method](work, seed=seed, **(options or {}))
    x = np.array([dict(zip(sol.names, sol.x))[k] for k in names])
    return x, sol, jacobian(x)


def reading_covariance(model: ChainModel, commands, motor_sigma, sigma: float | None = None,
                       segments=None, params: Mapping[str, float] | None = None) -> np.ndarray:
    """Covariance (rows, rows) mm^2 of the scale readings of a distance-measuring ``model`` when each pose is
    held at its commands plus independent motor motion errors of ``motor_sigma`` (M,) (deg / mm, 1 sigma):
    ``sigma^2 I + D diag_k(g_k S g_k^T) D^T`` with ``g_k`` the exact derivative of pose k's distance with
    respect to the motor commands (the model's ``mK.dzero`` columns: a zero offset is a command shift),
    ``S = diag(motor_sigma^2)`` and ``D`` :func:`reading_operator`. A motion error enters the readings before
    and after its pose: adjacent readings correlate (the paper 003 noise model, eq. 34-35, for any machine).
    """
    sigma = float(model.sigma_mm if sigma is None else sigma)
    commands = np.atleast_2d(commands)
    D = reading_operator(len(commands), model.reading_reference, segments)
    keys = [f"m{j + 1}.dzero" for j in range(commands.shape[1])]
    g = model.observation_jacobian(commands, params, keys)[:, 0, :]            # (N, M)
    motion = np.sum((g * np.asarray(motor_sigma, float)) ** 2, axis=1)
    return sigma**2 * np.eye(D.shape[0]) + (D * motion) @ D.T


def measured_jacobian(model: ChainModel, commands, params: Mapping[str, float] | None, keys: list[str],
                      segments=None) -> np.ndarray:
    """d (what the tracker measures of a campaign at ``commands`` (N, M)) / d ``keys``: (N*K*3, P) nest
    coordinates (:func:`flat_jacobian`), or for a model measuring a distance (rows, P) scale readings
    (:func:`reading_operator`, ``segments``); mm per key unit, NaN rows where the chain cannot assemble."""
    commands = np.atleast_2d(commands)
    if model.reading_reference is None:
        return flat_jacobian(model, commands, params, list(keys))
    return reading_operator(len(commands), model.reading_reference, segments) @ \
        model.observation_jacobian(commands, params, list(keys))[:, 0, :]


def structural_basis(model: ChainModel, commands, keys: list[str] | None = None, sigma: float | None = None,
                     rank_tol: float = RANK_TOL) -> BaseSet:
    """The base set of ``keys`` (default every error) on the nominal machine at a reference campaign
    ``commands`` (N, M) spread over the workspace: what the machine's structure lets any rich campaign
    identify, the same for every campaign (a campaign's own base set, :func:`identify_chain`, depends on its
    poses where it sees a direction weakly). Two identifications are compared in it (calibration history)."""
    keys = list(keys or model.error_keys)
    sigma = float(model.sigma_mm if sigma is None else sigma)
    J = measured_jacobian(model, commands, None, keys)
    J = J[np.isfinite(J).all(axis=1)] / sigma
    return base_parameters(J, keys, model.prior_std(keys), rank_tol)


def crlb(model: ChainModel, commands, params: Mapping[str, float] | None, keys: list[str],
         sigma: float | None = None, segments=None) -> np.ndarray:
    """Cramér-Rao standard deviations (len(keys),) of ``keys`` (their units) from a campaign at ``commands``
    (N, M) on the machine with errors ``params``, tracker noise ``sigma`` mm (default the model's):
    ``sqrt(diag(sigma^2 (J^T J)^-1))``; inf for keys the campaign does not determine (pass a base set).
    A model measuring a distance is read as scale readings (:func:`reading_operator`, ``segments``)."""
    sigma = float(model.sigma_mm if sigma is None else sigma)
    J = measured_jacobian(model, commands, params, keys, segments)
    J = J[np.isfinite(J).all(axis=1)] / sigma
    F = J.T @ J
    try:
        cov = np.linalg.inv(F)
    except np.linalg.LinAlgError:
        return np.full(len(keys), np.inf)
    d = np.diag(cov)
    return np.where(d > 0, np.sqrt(np.abs(d)), np.inf)


def compensate_targets(model: ChainModel, params: Mapping[str, float] | None, task) -> np.ndarray:
    """Commands (N, M) (deg / mm) that put the task site of the machine with the identified errors
    ``params`` at the task coordinates ``task`` (N, C); NaN rows where out of reach or outside a motor's
    range (the model's inverse kinematics)."""
    return model.inverse(np.atleast_2d(np.asarray(task, float)), params)
