"""The whole-closed-chain model at the command line: identification document and compensation.

Used by :mod:`pmcal.apps.ocpm_calib` when the model is ``full`` (the default). Units at the interface:
mm and degrees; the stiffness ratio is recorded beside the parameters (not a parameter key).
"""

from __future__ import annotations

import numpy as np

from pmcal.mechanism.ocpm.config import Geometry
from pmcal.mechanism.ocpm.data import Measurements
from pmcal.calib.ocpm.fullchain import FullChainOptions, identify_full, setpoints
from pmcal.mechanism.ocpm.params import LOG_RATIO, to_interface
from pmcal.twin.forward import FullChainModel
from pmcal.mechanism.rigid import fit_pose
from pmcal.mechanism.ocpm.params import ErrorSet, describe, is_angular
from pmcal.mechanism.rotations import tilt_torsion_angles

#: A parameter whose posterior std is above this fraction of its prior std is "not determined by the
#: campaign": the data moved it little, the prior (manufacturing tolerance) holds it.
UNDETERMINED_FRACTION = 0.7


def identify_document(meas: Measurements, sigma: float, source: str, geom: Geometry,
                      fit_stiffness_ratio: bool = True) -> tuple[dict[str, float], dict]:
    """Identify the whole chain; returns (params mm/deg, the rest of the params JSON)."""
    res = identify_full(meas, FullChainModel(geom),
                        FullChainOptions(fit_stiffness_ratio=fit_stiffness_ratio, sigma_mm=sigma))
    return result_document(res, meas, sigma, source, fit_stiffness_ratio)


def result_document(res, meas: Measurements, sigma: float, source: str, fit_stiffness_ratio: bool
                    ) -> tuple[dict[str, float], dict]:
    """(params mm/deg, the rest of the params JSON) of a whole-chain :class:`IdentResult`."""
    std = res.std
    prior = res.info["prior_std"]
    to_unit = lambda k, v: float(np.rad2deg(v)) if is_angular(k) else float(v)  # noqa: E731
    keys = [k for k in res.names if k != LOG_RATIO]
    idx = {k: i for i, k in enumerate(res.names)}
    undetermined = [k for k in keys if std[idx[k]] > UNDETERMINED_FRACTION * prior[idx[k]]]
    sv = res.info["singular_values"]
    doc = {
        "model": "full", "method": "map-least-squares",
        "stiffness_ratio": res.info["stiffness_ratio"],
        "stiffness_ratio_identified": fit_stiffness_ratio, "source": source,
        "uncertainty": {k: to_unit(k, std[idx[k]]) for k in keys},
        "prior_std": {k: to_unit(k, prior[idx[k]]) for k in keys},
        "identifiability": {
            "effective_parameters": res.info["effective_parameters"],
            "condition_number": float(sv[0] / sv[-1]) if sv[-1] > 0 else float("inf"),
            "not_determined_by_campaign": undetermined,
            "explanations": {k: describe(k) for k in undetermined},
            "note": "MAP fit with manufacturing-tolerance priors; 'not determined': posterior std above "
                    f"{UNDETERMINED_FRACTION:g} x prior std (held near the design value by the prior)",
        },
        "fit": {"n_poses": len(meas), "noise_sigma_mm": sigma,
                "residual_rms_mm": float(np.sqrt(np.mean(res.residuals**2))),
                "chi2_per_dof": res.info["chi2_per_dof"], "dof": res.info["dof"]},
        "solver": {"n_eval": res.n_eval, "n_iter": res.n_iter, "wall_time_s": res.wall_time,
                   "success": res.success, "message": res.message},
    }
    return to_interface(res.names, res.x), doc


class FullCompensation:
    """Commands and predictions of a machine described by whole-chain parameters (mm, deg)."""

    def __init__(self, params: dict[str, float], stiffness_ratio: float | None, geom: Geometry):
        self.errors = ErrorSet.from_dict(params, geom.n_limbs, geom.actuated)
        self.model = FullChainModel(geom, stiffness_ratio)
        self.ratio = self.model.stiffness_ratio
        self.geom = geom

    def commands_deg(self, phi_deg, theta_deg) -> np.ndarray:
        """Motor commands (N, 2) deg that point the machine at (phi, theta) deg; NaN if unreachable."""
        phi_deg, theta_deg = np.atleast_1d(phi_deg), np.atleast_1d(theta_deg)
        out = np.full((len(phi_deg), 2), np.nan)
        ok = theta_deg >= 0
        try:
            out[ok] = setpoints(self.model, self.errors, phi_deg[ok], theta_deg[ok], self.ratio)
        except ValueError:                 # a target beyond the workspace: commands NaN row by row
            for i in np.flatnonzero(ok):
                try:
                    out[i] = setpoints(self.model, self.errors, phi_deg[i:i + 1], theta_deg[i:i + 1], self.ratio)
                except ValueError:
                    pass
        return out

    def orientation(self, m_cmd_deg) -> tuple[np.ndarray, np.ndarray]:
        """(phi, theta) rad the machine reaches for commands (N, 2) deg."""
        self.model.set(self.errors, self.ratio)
        T, _ = self.model.predict(m_cmd_deg)
        _, R, _ = fit_pose(T, self.geom.targets)
        return tilt_torsion_angles(R)
