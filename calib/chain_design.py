"""Which poses to measure: a D-optimal identification campaign for a closed-chain machine.

Candidates are drawn over the machine's workspace (its inverse kinematics, motor ranges); the base set of
errors the candidates can determine is found as identification finds it (:func:`base_parameters` on the
whitened, prior-scaled Jacobian); then ``n_poses`` candidates are chosen to maximise ``log det`` of the
posterior information of the base parameters (Bayesian D-optimality: the data's information plus the
prior's, :func:`pmcal.calib.pose_selection.select_poses`, greedy start and Fedorov exchange). The chosen
poses are ordered for driving: a nearest-neighbour tour in motor space from the home configuration.

Units: commands deg / mm per motor; uncertainties in each error's unit (mm / deg).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pmcal.calib.chain_model import ChainModel
from pmcal.calib.closed_chain import RANK_TOL, base_parameters, base_prior_cov, flat_jacobian
from pmcal.calib.pose_selection import select_poses

#: candidate poses per pose to choose that make a good pool (at least :data:`POOL_MIN`)
POOL_FACTOR = 6
POOL_MIN = 240


@dataclass
class CampaignDesign:
    """A planned campaign (:func:`design_campaign`).

    commands : (n, M) motor commands in driving order, deg / mm.
    base : the base errors of the candidate pool, in which the poses are chosen and :attr:`covariance` is
        given.
    determined : how many base errors the chosen poses determine (the rank ``identify`` finds on the plan's
        own poses: it may be smaller than ``len(base)`` where a machine's directions thin out without a gap,
        as on CAD models whose loops barely see some errors).
    covariance : (len(base), len(base)) posterior covariance of the base errors after the planned campaign
        (data and prior, at the nominal machine), their units.
    std : its standard deviations.
    std_random : the same for ``n`` poses drawn at random from the pool (the campaign ``twin measure``
        draws), for comparison.
    pool : number of candidate poses.
    """

    commands: np.ndarray
    base: list[str]
    covariance: np.ndarray
    std: np.ndarray
    std_random: np.ndarray
    pool: int
    determined: int = 0

    @property
    def gain(self) -> float:
        """Geometric mean over the base errors of ``std_random / std``: how many times smaller the planned
        campaign's uncertainty is than a random one's of the same size."""
        return float(np.exp(np.mean(np.log(self.std_random / self.std))))


def _posterior_cov(blocks: np.ndarray, prior_info: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Posterior covariance in the base errors' units of the poses ``blocks`` (prior-scaled)."""
    info = np.einsum("kci,kcj->ij", blocks, blocks) + prior_info
    return np.linalg.inv(info) * np.outer(scale, scale)


def _std(cov: np.ndarray) -> np.ndarray:
    return np.sqrt(np.clip(np.diag(cov), 0.0, None))


def _driving_order(commands: np.ndarray, start: np.ndarray, span: np.ndarray) -> np.ndarray:
    """Indices of a nearest-neighbour tour through ``commands`` from ``start`` (distances in motor
    ranges, the largest motor move counting)."""
    left = list(range(len(commands)))
    here, order = start, []
    while left:
        d = np.max(np.abs(commands[left] - here) / span, axis=1)
        i = left.pop(int(np.argmin(d)))
        order.append(i)
        here = commands[i]
    return np.array(order, int)


def design_campaign(model: ChainModel, candidates: np.ndarray, n_poses: int, *, start: np.ndarray | None = None,
                    sigma_mm: float | None = None) -> CampaignDesign:
    """Choose ``n_poses`` of the ``candidates`` that determine the machine's errors best (module docstring).

    Parameters
    ----------
    model : the machine (:class:`~pmcal.calib.chain_model.ChainModel`).
    candidates : (n, M) motor commands the machine can reach, deg / mm (e.g. drawn over its workspace;
        :data:`POOL_FACTOR` per pose to choose is plenty).
    n_poses : poses to choose; enough coordinates for the base set.
    start : (M,) commands the tour starts from (default the first candidate).
    sigma_mm : tracker noise, mm (default the model's).

    Returns
    -------
    CampaignDesign

    Examples
    --------
    >>> from pmcal.twin.closed_chain import ClosedChainTwin                     # doctest: +SKIP
    >>> twin = ClosedChainTwin.from_folder("mjcf/delta_3dof")                   # doctest: +SKIP
    >>> pool = twin.sample_commands(240, np.random.default_rng(1))             # doctest: +SKIP
    >>> plan = design_campaign(twin, pool, 24, start=twin.home_commands)       # doctest: +SKIP
    >>> plan.commands.shape, plan.gain > 1                                     # doctest: +SKIP
    ((24, 3), True)
    """
    candidates = np.atleast_2d(np.asarray(candidates, float))
    if not 1 <= n_poses <= len(candidates):
        raise ValueError(f"cannot choose {n_poses} poses from {len(candidates)} candidates")
    sigma = float(model.sigma_mm if sigma_mm is None else sigma_mm)
    keys = list(model.error_keys)
    J = flat_jacobian(model, candidates, None, keys) / sigma
    if not np.isfinite(J).all():
        raise ValueError("the nominal machine cannot assemble some candidates")
    basis = base_parameters(J, keys, model.prior_std(keys), RANK_TOL)
    idx = [keys.index(k) for k in basis.base]
    cov = base_prior_cov(model, basis)
    scale = np.sqrt(np.diag(cov))                       # base errors in units of their prior size
    blocks = J[:, idx].reshape(len(candidates), -1, len(idx)) * scale
    prior_info = np.linalg.inv(cov / np.outer(scale, scale))
    if n_poses * blocks.shape[1] < len(idx):
        need = -(-len(idx) // blocks.shape[1])
        raise ValueError(f"{n_poses} poses give {n_poses * blocks.shape[1]} coordinates for {len(idx)} base errors: "
                         f"plan at least {need} poses")
    chosen = select_poses(blocks, n_poses, "D", prior=prior_info)
    span = np.ptp(candidates, axis=0)
    span = np.where(span > 0, span, 1.0)
    tour = _driving_order(candidates[chosen], candidates[0] if start is None else np.asarray(start, float), span)
    chosen = chosen[tour]
    cov = _posterior_cov(blocks[chosen], prior_info, scale)
    rows = J.reshape(len(candidates), -1, J.shape[1])[chosen].reshape(-1, J.shape[1])
    return CampaignDesign(commands=candidates[chosen], base=list(basis.base), covariance=cov, std=_std(cov),
                          std_random=_std(_posterior_cov(blocks[:n_poses], prior_info, scale)),
                          pool=len(candidates), determined=base_parameters(rows, keys, model.prior_std(keys)).rank)
