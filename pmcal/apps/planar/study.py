"""Monte Carlo studies of the zero-offset calibration on the twin (paper section 6; demo and benchmark).

For one error set, S noise realisations of the whole loop (identify, compensate, repeat) run in lockstep
on one twin. Outcomes are in the paper's terms: compensation values and their error δ (deg), MAEMM error
δM (mm), Δp0 and Δp_max before and after calibration (mm), condition numbers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pmcal.calib.planar.calibration import CalibrationRun, calibrate_many
from pmcal.mechanism.planar.geometry import Errors
from pmcal.mechanism.planar.kinematics import forward
from pmcal.mechanism.planar.noise import Noise
from pmcal.twin.planar.twin import PlanarTwin, batch_measure, commands_for


@dataclass
class StudyResult:
    """S runs of the loop on one machine (deg and mm unless named otherwise)."""

    errors: Errors
    positions: np.ndarray          # (K, 2) mm
    method: str
    comp_deg: np.ndarray           # (S, 2) compensation values
    delta_deg: np.ndarray          # (S, 2) |compensation - set value|
    delta_M: np.ndarray            # (S, 2) |identified MAEMM - set value|, mm
    m: np.ndarray                  # (S,) compensation number used
    converged: np.ndarray          # (S,)
    dp0_before: float
    dp0_after: np.ndarray          # (S,)
    dpmax_before: float
    dpmax_after: np.ndarray        # (S,)
    cond_first: np.ndarray         # (S,) κ1
    cond_later: np.ndarray         # (S,) mean κ of identifications 2..m (NaN if m = 1)
    runs: list[CalibrationRun]

    def summary(self) -> dict:
        """Medians and RMS over the runs (JSON-ready)."""
        rms = lambda a: float(np.sqrt(np.mean(np.square(a))))  # noqa: E731
        return {
            "runs": int(len(self.m)),
            "delta_deg_median": [float(v) for v in np.median(self.delta_deg, axis=0)],
            "delta_deg_rms": [rms(self.delta_deg[:, 0]), rms(self.delta_deg[:, 1])],
            "delta_deg_p95": [float(v) for v in np.percentile(self.delta_deg, 95, axis=0)],
            "delta_M_median_mm": [float(v) for v in np.median(self.delta_M, axis=0)],
            "dp0_before_mm": self.dp0_before,
            "dp0_after_median_mm": float(np.median(self.dp0_after)),
            "dp0_after_p95_mm": float(np.percentile(self.dp0_after, 95)),
            "dpmax_before_mm": self.dpmax_before,
            "dpmax_after_median_mm": float(np.median(self.dpmax_after)),
            "cond_first": float(np.median(self.cond_first)),
            "cond_later_mean": float(np.nanmedian(self.cond_later)) if np.any(np.isfinite(self.cond_later)) else None,
            "m_median": float(np.median(self.m)),
            "converged_fraction": float(np.mean(self.converged)),
        }


def run_study(errors: Errors, positions: np.ndarray, noise: Noise, runs: int, *, seed: int = 0,
              method: str = "tsvd", mu0: float = np.deg2rad(0.1), max_iter: int = 19,
              stop: bool | np.ndarray = True, correct_maemm: bool = True,
              twin: PlanarTwin | None = None) -> StudyResult:
    """``runs`` noise realisations of the calibration loop on the twin of ``errors`` at ``positions``.

    ``stop`` (per run or for all): stop at convergence, or run on to ``max_iter`` (Fig. 9); either way a
    run's compensation value is the one at its compensation number m."""
    twin = twin if twin is not None else PlanarTwin(errors)
    geom = twin.machine.geometry
    rng = np.random.default_rng(seed)
    out = calibrate_many(geom, positions, batch_measure(twin, noise, rng), runs, mu0=mu0, max_iter=max_iter,
                         stop=stop, correct_maemm=correct_maemm, method=method, noise=noise)
    comp = np.array([r.comp for r in out])
    drM = np.array([r.drM for r in out])
    P0 = forward(geom, geom.home)
    home_cmd = np.concatenate([geom.home[None], geom.home[None] - comp])
    home = twin.assemble(home_cmd).r
    dp0 = np.linalg.norm(home - P0, axis=1)
    dp = evaluate_at(twin, positions, np.rad2deg(np.concatenate([np.zeros((1, 2)), comp])))
    cond1 = np.array([r.steps[0].cond for r in out])
    condm = np.array([np.mean([s.cond for s in r.steps[1:r.m]]) if r.m > 1 else np.nan for r in out])
    return StudyResult(
        errors=errors, positions=np.asarray(positions, dtype=float), method=method,
        comp_deg=np.rad2deg(comp), delta_deg=np.abs(np.rad2deg(comp - errors.dtheta)),
        delta_M=np.abs(drM - errors.drM), m=np.array([r.m for r in out]),
        converged=np.array([r.converged for r in out]), dp0_before=float(dp0[0]), dp0_after=dp0[1:],
        dpmax_before=float(dp[0]), dpmax_after=dp[1:], cond_first=cond1, cond_later=condm, runs=out)


# ----------------------------------------------------------------------------------------------------------
# The paper's simulation study (section 6) and this project's comparison, shared by the demo and the benchmark.

#: the paper's published numbers (Mei et al. 2017), for side-by-side tables
PAPER = {
    "table3": {  # group: (comp dtheta1, delta1, comp dtheta2, delta2, dp0 before, dp0 after) deg, mm
        "group1": (2.033, 0.033, -0.957, 0.043, 10.933, 0.402),
        "group2": (-1.049, 0.049, 0.463, 0.037, 5.482, 0.423),
        "group3": (0.536, 0.036, 0.297, 0.047, 3.796, 0.434),
        "group4": (2.024, 0.024, -0.978, 0.022, 10.896, 0.228),
        "group5": (-1.025, 0.025, 0.474, 0.026, 5.5195, 0.256),
        "group6": (0.476, 0.024, 0.225, 0.025, 3.798, 0.239),
    },
    "table4": {"group1": (12.906, 0.493), "group2": (6.418, 0.531), "group3": (4.672, 0.533),
               "group4": (12.868, 0.279), "group5": (6.455, 0.314), "group6": (4.663, 0.293)},
    "table5": {"group1": (0.069, 0.040), "group2": (0.074, 0.045), "group3": (0.071, 0.042),
               "group4": (0.044, 0.022), "group5": (0.051, 0.028), "group6": (0.047, 0.024)},
    "table6": {"group1": 472.47, "group2": 472.49, "group3": 472.49, "group4": 472.50, "group5": 472.51,
               "group6": 472.50},
    "fig8": {"n": 3, "kappa1": 475.34, "kappam": 472.54},
}
GROUPS = tuple(f"group{i}" for i in range(1, 7))


@dataclass
class Setting:
    """One way of calibrating: positions, identification method, noise of the campaign."""

    name: str
    label: str
    positions: np.ndarray
    method: str
    noise: Noise


def settings(machine, paper_positions: np.ndarray, ours_positions: np.ndarray) -> list[Setting]:
    """The three settings compared: the paper's method under the paper's noise (eq. 34-35), the paper's method
    with the scale noise alone (the reading under which the paper's Table 3 is reproduced), and this
    project's positions + GLS under the full noise."""
    full = machine.noise
    return [
        Setting("seed", "paper method (K=6 on W, TSVD), noise eq. 34-35", paper_positions, "tsvd", full),
        Setting("paper_scale_only", "paper method, scale noise only (servo off)", paper_positions, "tsvd",
                Noise(scale=full.scale, servo=0.0)),
        Setting("ours", f"noise-optimal positions (K={len(ours_positions)}) + GLS, noise eq. 34-35",
                ours_positions, machine.design.method, full),
    ]


def evaluate_at(twin: PlanarTwin, positions: np.ndarray, comp_deg: np.ndarray) -> np.ndarray:
    """Largest position error (mm) over ``positions`` for each compensation (S, 2) deg (Table 4)."""
    cmd = commands_for(twin, positions)[None] - np.deg2rad(comp_deg)[:, None, :]
    reached = twin.assemble(cmd.reshape(-1, 2)).r.reshape(len(comp_deg), len(positions), 2)
    return np.linalg.norm(reached - positions, axis=-1).max(axis=1)
