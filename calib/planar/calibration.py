"""Repeated identification with the MAEMM correction (eq. 30) and iterative zero-offset compensation
(eq. 32-33), with the machine in the loop through a measurement callback (no I/O here).

Identification j measures the K positions with the motor commands ``θ_k = IK(r_k) - Δθ_comp`` (the
controller's kinematic model compensated with the zero offsets found so far), identifies the remaining
zero offsets ``Δθ^(j)`` and MAEMM ``ΔrM^(j)`` (for j ≥ 2 with the mechanism corrected by the MAEMM found
so far, eq. 30), and adds them. The compensation value after m identifications is
``Δθ_i = Δθ_i^(1) + ... + Δθ_i^(m)`` (eq. 33). The loop stops when the compensation accuracy

    μ^(j) = sqrt( ((Δθ1^(j) - Δθ1^(j-1))^2 + (Δθ2^(j) - Δθ2^(j-1))^2) / 2 )        (eq. 32)

falls below μ0 (seed: 0.1°). Units: rad and mm.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from pmcal.mechanism.planar.geometry import Errors, Geometry
from pmcal.calib.planar.identification import identify
from pmcal.mechanism.planar.kinematics import actual_position, forward, inverse
from pmcal.mechanism.planar.noise import Noise
from pmcal.calib.solvers.result import IdentResult

#: ``measure(theta_cmd)``: commands (K, 2) rad -> scale changes between adjacent positions (K-1,) mm
Measure = Callable[[np.ndarray], np.ndarray]


@dataclass
class Step:
    """One identification of the loop (rad, mm)."""

    result: IdentResult
    dtheta: np.ndarray          # Δθ^(j): zero offsets found by this identification
    drM: np.ndarray             # ΔrM^(j): MAEMM found by this identification (remaining part if corrected)
    comp: np.ndarray            # compensation value after this identification (eq. 33)
    drM_total: np.ndarray       # MAEMM estimate after this identification
    mu: float                   # eq. 32 (NaN for the first identification)
    cond: float                 # condition number of G (eq. 31)


@dataclass
class CalibrationRun:
    """The loop's history; ``m`` identifications were used for the compensation value."""

    steps: list[Step] = field(default_factory=list)
    converged: bool = False
    m: int = 0

    @property
    def comp(self) -> np.ndarray:
        """Compensation value Δθ (2,) rad (eq. 33)."""
        return self.steps[self.m - 1].comp

    @property
    def drM(self) -> np.ndarray:
        """MAEMM estimate (2,) mm."""
        return self.steps[self.m - 1].drM_total

    def history(self) -> dict[str, np.ndarray]:
        """Arrays over the identifications: ``comp`` (j, 2) rad, ``drM`` (j, 2) mm, ``mu`` (j,), ``cond`` (j,)."""
        return {"comp": np.array([s.comp for s in self.steps]),
                "drM": np.array([s.drM_total for s in self.steps]),
                "mu": np.array([s.mu for s in self.steps]),
                "cond": np.array([s.cond for s in self.steps])}


def calibrate(geom: Geometry, r: np.ndarray, measure: Measure, *, mu0: float = np.deg2rad(0.1),
              max_iter: int = 19, stop: bool = True, correct_maemm: bool = True, method: str = "tsvd",
              rank: int | None = None, noise: Noise | None = None) -> CalibrationRun:
    """Run the paper's zero-offset calibration at nominal positions ``r`` (K, 2) mm.

    ``stop=False`` runs all ``max_iter`` identifications (the paper's robustness study, Fig. 9) and reports
    in ``m`` where the stopping rule would have stopped (``max_iter`` if never). ``correct_maemm=False``
    identifies the MAEMM afresh each time without correcting the mechanism (eq. 29 throughout).
    """
    def batch_measure(cmd: np.ndarray, ids: np.ndarray) -> np.ndarray:
        return np.asarray(measure(cmd[0]), dtype=float)[None]

    return calibrate_many(geom, r, batch_measure, 1, mu0=mu0, max_iter=max_iter, stop=stop,
                          correct_maemm=correct_maemm, method=method, rank=rank, noise=noise)[0]


#: ``measure(theta_cmd, ids)``: commands (S, K, 2) rad of the runs ``ids`` (S,) still going -> readings (S, K-1) mm
BatchMeasure = Callable[[np.ndarray, np.ndarray], np.ndarray]


def calibrate_many(geom: Geometry, r: np.ndarray, measure: BatchMeasure, n_runs: int, *,
                   mu0: float = np.deg2rad(0.1), max_iter: int = 19, stop: bool | np.ndarray = True,
                   correct_maemm: bool = True, method: str = "tsvd", rank: int | None = None,
                   noise: Noise | None = None) -> list[CalibrationRun]:
    """:func:`calibrate` for ``n_runs`` independent runs in lockstep (one measurement call per identification
    for all runs still going: a twin assembles them together). ``stop`` may be given per run (n_runs,)."""
    stop = np.broadcast_to(np.asarray(stop, dtype=bool), (n_runs,))
    theta_nom = inverse(geom, r)
    if not np.all(np.isfinite(theta_nom)):
        raise ValueError("a measurement position is out of reach of the nominal robot")
    comp = np.zeros((n_runs, 2))
    drM_total = np.zeros((n_runs, 2))
    prev = np.full((n_runs, 2), np.nan)
    runs = [CalibrationRun() for _ in range(n_runs)]
    active = np.arange(n_runs)
    for j in range(1, max_iter + 1):
        if active.size == 0:
            break
        readings = np.asarray(measure(theta_nom[None] - comp[active, None, :], active), dtype=float)
        for a, i in enumerate(active):
            corr = drM_total[i] if (correct_maemm and j > 1) else None
            res = identify(geom, r, readings[a], method=method, rank=rank, drM=corr, noise=noise)
            inc, drm = res.x[:2].copy(), res.x[2:4].copy()
            comp[i] += inc
            drM_total[i] = drM_total[i] + drm if correct_maemm else drm
            mu = float(np.sqrt(np.sum((inc - prev[i]) ** 2) / 2.0)) if j > 1 else float("nan")
            runs[i].steps.append(Step(res, inc, drm, comp[i].copy(), drM_total[i].copy(), mu,
                                      float(res.info["cond"])))
            prev[i] = inc
            if not runs[i].converged and j > 1 and mu < mu0:
                runs[i].converged, runs[i].m = True, j
        active = np.array([i for i in active if not (stop[i] and runs[i].converged)], dtype=int)
    for run in runs:
        if not run.converged:
            run.m = len(run.steps)
    return runs


def position_errors(geom: Geometry, err: Errors, r: np.ndarray, comp: np.ndarray | None = None) -> np.ndarray:
    """Absolute position errors |r' - r| (mm) of the real machine ``err`` sent to the nominal positions
    ``r`` (..., 2) by a controller compensated with zero offsets ``comp`` (rad)."""
    cmd = inverse(geom, r) - (np.zeros(2) if comp is None else comp)
    return np.linalg.norm(actual_position(geom, err, cmd) - r, axis=-1)


def home_error(geom: Geometry, err: Errors, comp: np.ndarray | None = None) -> float:
    """Δp0: absolute position error (mm) at the home position P0 (θ1 = 0, θ2 = 180°), paper Table 3."""
    return float(position_errors(geom, err, forward(geom, geom.home), comp))
