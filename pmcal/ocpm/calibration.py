"""Identification of the over-constrained PM and its result, :class:`Calibration`.

Two models (``model=``): ``"full"`` (default), the whole closed chain — every limb, the SS limb, motor
zero offsets and the closure stiffness ratio, fitted by MAP least squares on the raw target coordinates
through the twin's forward model; ``"paper"``, the per-limb model of Sun et al. 2018 (limbs 1 and 2,
eq. 14), solved by one of the paper's methods (``method=``: HGA by default) with the platform position
map fitted afterwards. Units at this interface: mm and degrees.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from datetime import datetime
from functools import cached_property
from pathlib import Path

import numpy as np
from scipy.linalg import block_diag

from pmcal import progress
from pmcal.bridge.comptable import CompTable
from pmcal.campaign_quality import judge, paper_quality
from pmcal.calib.ocpm import compensation as comp
from pmcal.calib.ocpm import paper_calibration
from pmcal.calib.ocpm import paper_model as pm
from pmcal.calib.ocpm.fullchain import platform_normals
from pmcal.calib.solvers import METHODS
from pmcal.ocpm.compensators import (DEFAULT_GRID, Compensator, FullCompensation, PaperCompensation, build_table,
                                checked_commands)
from pmcal.errors import InputError, RunError
from pmcal.export_model import ExportParts
from pmcal.fileio import check_output
from pmcal.threads import blas_policy
from pmcal.history import LOG_UNIT, UNDETERMINED_FRACTION, make_record
from pmcal.ocpm.io import PARAM_MODELS, param_unit, paper_keys_only, read_params, write_params
from pmcal.mechanism.ocpm.config import MACHINE_DIR, Geometry, default_geometry
from pmcal.mechanism.ocpm.data import Measurements
from pmcal.mechanism.ocpm.kinematics import limb_ik, nominal_ik
from pmcal.mechanism.ocpm.params import LOG_RATIO, ErrorSet, describe, is_angular, to_interface
from pmcal.ocpm.tracker_frame import identify_result, tracker_document
from pmcal.twin.ocpm.forward import FullChainModel
from pmcal.twin.ocpm.machine import Twin
from pmcal.twin.ocpm.model import MM, MODEL_XML, build_model, load_model

#: Calibration models: the one list, shared with the parameters-file schema.
MODELS = PARAM_MODELS
DEFAULT_MODEL = "full"
DEFAULT_METHOD = "hga"
#: Fewest poses the whole-chain fit accepts: ~40 effective parameters, 6 pose coordinates a pose.
MIN_POSES_FULL = 12


@dataclass
class Calibration:
    """The identified machine: parameters, their uncertainty, the model used, and its compensation.

    Attributes
    ----------
    params : dict of str to float
        Identified parameters in interface units (mm, deg), keys as in ``docs/formats.md``; an absent key
        is nominal (zero error).
    model : str
        ``"full"`` (whole closed chain) or ``"paper"`` (per-limb model of the paper).
    method : str
        Solver: ``"map-least-squares"`` for the whole chain, the paper's method name otherwise.
    document : dict
        Everything else the parameters file records: uncertainty (1 sigma, mm/deg), identifiability,
        fit statistics (``fit.residual_rms_mm`` or ``fit.residual_rms_sigma``), solver report,
        ``quality`` (how much the campaign determines and whether the result is usable:
        :mod:`pmcal.campaign_quality`), and for the whole chain ``stiffness_ratio``; for the paper model
        ``position_map``.
    names : list of str
        Parameter keys of ``covariance`` (internal order; may include ``log_stiffness_ratio``).
    covariance : ndarray or None
        Posterior covariance over ``names`` in internal units (mm, rad); None when loaded from a file
        that did not record it.
    residuals : ndarray or None
        Fit residuals (mm for the whole chain, whitened for the paper model); None when loaded.
    geometry : Geometry
        Nominal geometry the parameters refer to.
    solution : object or None
        The solver's own result (``IdentResult`` for the whole chain, ``PaperCalibration`` with the
        per-limb results for the paper model); None when loaded from a file.

    Examples
    --------
    >>> import pmcal
    >>> meas = pmcal.read_measurements("m.csv")                      # doctest: +SKIP
    >>> cal = pmcal.identify(meas)                                   # doctest: +SKIP
    >>> cal.setpoints([0.0, 90.0], [10.0, 30.0]).shape               # doctest: +SKIP
    (2, 2)
    """

    params: dict[str, float]
    model: str
    method: str
    document: dict = field(default_factory=dict)
    names: list[str] = field(default_factory=list)
    covariance: np.ndarray | None = None
    residuals: np.ndarray | None = None
    geometry: Geometry = field(default_factory=default_geometry, repr=False)
    solution: object | None = field(default=None, repr=False)

    @cached_property
    def compensator(self) -> Compensator:
        """The compensation of this calibration (one type per model)."""
        geom = self.geometry
        if self.model == "full":
            return FullCompensation(self.params, self.document.get("stiffness_ratio"), geom)
        errors = ErrorSet.from_dict(self.params, geom.n_limbs, geom.actuated)
        pmap = self.document.get("position_map")
        return PaperCompensation(errors, comp.PositionMap.from_dict(pmap) if pmap is not None else None, geom)

    @blas_policy()
    def setpoints(self, phi_deg, theta_deg=None) -> np.ndarray:
        """Motor commands (n, 2) deg that point the calibrated machine at the orientations (deg).

        Parameters
        ----------
        phi_deg, theta_deg : array_like
            Azimuth and tilt (tilt-torsion angles, base frame), degrees; or ``phi_deg`` alone an (n, 2)
            array of targets ``[phi, theta]`` (the task coordinates, as every machine's ``setpoints`` takes).

        Raises
        ------
        pmcal.errors.InputError
            Naming the first orientation out of reach or needing commands outside the motor limits.
        """
        if theta_deg is None:
            task = np.atleast_2d(np.asarray(phi_deg, float))
            if task.ndim != 2 or task.shape[1] != 2:
                raise InputError(f"targets need 2 columns (phi_deg, theta_deg), got shape {task.shape}",
                                 field="targets")
            phi_deg, theta_deg = task[:, 0], task[:, 1]
        phi, theta = np.atleast_1d(np.asarray(phi_deg, float)), np.atleast_1d(np.asarray(theta_deg, float))
        if phi.shape != theta.shape:
            raise InputError(f"phi_deg has {phi.size} values, theta_deg {theta.size}", field="theta_deg")
        return checked_commands(self.compensator, phi, theta, self.geometry)

    @blas_policy()
    def compensation_table(self, version: int | None = None, grid: tuple[int, int] = DEFAULT_GRID) -> CompTable:
        """The PLC's compensation table over phi 0..360 deg and theta 0..theta_max (validated).

        ``version`` (1..2**32-1) defaults to the current Unix time; ``grid`` is (n_phi, n_theta).
        """
        version = int(time.time()) if version is None else int(version)
        return build_table(self.compensator, self.geometry, grid, version)

    def save(self, path: str | Path) -> Path:
        """Write the parameters file (JSON, ``docs/formats.md``), atomically, after the output guard
        (:func:`pmcal.fileio.check_output`); returns the path."""
        check_output(path, suffixes=(".json",))
        extra = dict(self.document, model=self.model, method=self.method)
        if self.covariance is not None:
            extra["covariance"] = {"names": list(self.names), "unit": "mm, rad (log for the stiffness ratio)",
                                   "matrix": np.asarray(self.covariance).tolist()}
        write_params(path, self.params, **extra)
        return Path(path)

    @classmethod
    def load(cls, path: str | Path, geometry: Geometry | None = None) -> "Calibration":
        """Read a parameters file written by :meth:`save` or ``pmcal identify``."""
        geom = geometry or default_geometry()
        params, doc = read_params(path, geom)           # validates model name and stiffness ratio
        model = doc.get("model")
        if model is None:            # a file without "model": the paper's if it holds only the paper's keys
            model = "paper" if "position_map" in doc or paper_keys_only(params) else DEFAULT_MODEL
        pmap = doc.get("position_map")
        if model == "paper" and pmap is not None:
            try:
                comp.PositionMap.from_dict(pmap)
            except (KeyError, TypeError, ValueError) as exc:
                raise InputError(f"invalid position map ({exc})", file=str(path), field="position_map") from None
        cov = doc.pop("covariance", None)
        names, matrix = [], None
        if isinstance(cov, dict) and "matrix" in cov:
            names, matrix = list(cov.get("names", [])), np.asarray(cov["matrix"], float)
        method = str(doc.pop("method", "map-least-squares" if model == "full" else DEFAULT_METHOD))
        doc.pop("model", None)
        return cls(params=params, model=model, method=method, document=doc, names=names, covariance=matrix,
                   geometry=geom)


# ================================================================================ identification
def check_choice(value: str | None, default: str, known, option: str) -> str:
    """``value`` (or ``default``) if it is one of ``known``, else InputError naming ``option``."""
    value = default if value is None else value
    if value not in known:
        raise InputError(f"unknown {option.lstrip('-')} '{value}' (known: {', '.join(known)})", field=option)
    return value


def check_sigma(sigma: float | None, geom: Geometry) -> float:
    """Tracker noise (mm), default from the machine configuration; InputError unless positive."""
    sigma = geom.sigma_mm if sigma is None else float(sigma)
    if not (np.isfinite(sigma) and sigma > 0):
        raise InputError(f"tracker noise must be a positive number of mm, got {sigma}", field="--sigma")
    return sigma


def check_reachable(meas: Measurements, path: str | None, geom: Geometry) -> None:
    """Every measured pose must be within reach of the actuated limbs of the nominal machine."""
    r, R, _ = meas.poses(geom)
    ik = limb_ik(r, R, None, geom, (1, 2))
    bad = np.argwhere(~np.isfinite(ik.beta) & np.isfinite(r).all(axis=1)[:, None])   # NaN r: blocked target
    if bad.size:
        i, j = (int(v) for v in bad[0])
        raise InputError(f"the measured platform pose is out of reach of limb {j + 1} (|K/rho| = "
                         f"{abs(ik.reach[i, j]):.3g} > 1): not a pose of this machine", file=path, row=i + 1,
                         field="t1_x")


@blas_policy()
def identify(meas: Measurements, *, model: str = DEFAULT_MODEL, method: str | None = None,
             sigma_mm: float | None = None, rng_seed: int | None = 0, fit_stiffness_ratio: bool = True,
             source: str | None = None, geometry: Geometry | None = None, frame: str = "base",
             registration=None, nest_tolerance_mm: float = 0.5, robust: bool | None = None) -> Calibration:
    """Calibrate the over-constrained PM from a measurement campaign.

    Parameters
    ----------
    meas : Measurements
        The campaign (:func:`pmcal.read_measurements`): commanded motor angles and measured targets, mm,
        base frame.
    model : {"full", "paper"}
        ``"full"``: the whole closed chain (every limb, SS, zero offsets, stiffness ratio), MAP least
        squares. ``"paper"``: the per-limb model of Sun et al. 2018 for limbs 1 and 2.
    method : str, optional
        Solver of the paper model (``pmcal.calib.solvers.METHODS``; default ``"hga"``, the paper's
        hybrid genetic algorithm). Not used by the whole chain.
    sigma_mm : float, optional
        Tracker noise, 1 sigma per coordinate, mm (default: the machine's, 0.01 mm).
    rng_seed : int or None
        Seed of the random generator of the population methods (paper model).
    fit_stiffness_ratio : bool
        Identify the closure stiffness ratio with the whole chain.
    source : str, optional
        Where the data came from (recorded; named in error messages).
    frame : {"base", "tracker"}
        Frame of the measured targets. ``"tracker"``: the tracker's own frame; the pose of the base
        frame in it (registration) and the target nests' offsets are identified with the machine, the
        base frame fixed to the motor axes (``docs/tracker_frame.md``). Whole-chain model only.
    registration : (R (3, 3), t (3,) mm), optional
        Start value of the registration (default: from the data).
    nest_tolerance_mm : float
        Prior of the nests' offsets from the drawing, 1 sigma per coordinate, mm (tracker frame).
    robust : bool, optional
        Robust fit with named outlier rejection (default: on in the tracker frame and with blocked targets).

    Returns
    -------
    Calibration

    Raises
    ------
    pmcal.errors.InputError
        Too few poses, poses out of reach, an unknown model or method, a non-positive noise, a bad
        campaign (more outliers than the robust fit may reject).

    Examples
    --------
    >>> import pmcal
    >>> cal = pmcal.identify(pmcal.read_measurements("m.csv"))        # doctest: +SKIP
    >>> cal.params["L1.dbx"]                                          # doctest: +SKIP
    -1.49
    """
    geom = geometry or default_geometry()
    model = check_choice(model, DEFAULT_MODEL, MODELS, "--model")
    frame = check_choice(frame, "base", ("base", "tracker"), "--frame")
    sigma = check_sigma(sigma_mm, geom)
    if model != "full" and frame != "base":
        raise InputError("--frame tracker needs the whole-chain model (--model full)", field="--frame")
    if model == "full":
        if method is not None:
            raise InputError("--method chooses the solver of --model paper; the whole-chain model is fitted "
                             "by MAP least squares (give --model paper to use the paper's methods)",
                             field="--method")
        if len(meas) < MIN_POSES_FULL:
            raise InputError(f"{len(meas)} poses are too few for the whole-chain model: measure at least "
                             f"{MIN_POSES_FULL} (24-48 recommended, docs/fullchain.md)", file=source,
                             field="pose_id")
        if frame == "base":
            check_reachable(meas, source, geom)
        model_ = FullChainModel(geom)
        res = identify_result(meas, model_, sigma, frame, registration, nest_tolerance_mm, robust,
                              fit_stiffness_ratio, source)
        cal = _identify_full(res, meas, sigma, source or "", geom, fit_stiffness_ratio)
        cal.document["quality"] = full_chain_quality(model_, res, geom)
        return cal
    method = check_choice(method, DEFAULT_METHOD, METHODS, "--method")
    n_free = len(pm.PAPER_LIMB_FIELDS)
    if len(meas) <= n_free:
        raise InputError(f"{len(meas)} poses cannot determine {n_free} parameters a limb: measure at least "
                         f"{n_free + 1} (the paper uses 24)", file=source, field="pose_id")
    check_reachable(meas, source, geom)
    return _identify_paper(meas, method, sigma, rng_seed, source or "", geom)


def _identify_full(res, meas: Measurements, sigma: float, source: str, geom: Geometry,
                   fit_stiffness_ratio: bool) -> Calibration:
    std, prior = res.std, res.info["prior_std"]
    to_unit = lambda k, v: float(np.rad2deg(v)) if is_angular(k) else float(v)  # noqa: E731
    keys = [k for k in res.names if k != LOG_RATIO]
    idx = {k: i for i, k in enumerate(res.names)}
    undetermined = [k for k in keys if std[idx[k]] > UNDETERMINED_FRACTION * prior[idx[k]]]
    sv = res.info["singular_values"]
    doc = {
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
        **tracker_document(res, meas),
    }
    return Calibration(params=to_interface(res.names, res.x), model="full", method="map-least-squares",
                       document=doc, names=list(res.names), covariance=res.covariance,
                       residuals=np.asarray(res.residuals), geometry=geom, solution=res)


def _identify_paper(meas: Measurements, method: str, sigma: float, rng_seed: int | None, source: str,
                    geom: Geometry) -> Calibration:
    with progress.progress(total=2, desc=f"identify ({method})", unit="limb") as bar:
        cal = paper_calibration.calibrate(meas, method, (1, 2), seed=rng_seed, sigma_mm=sigma, geom=geom,
                           on_limb_done=lambda j, res: bar.update(1))
    pmap = comp.fit_position_map(cal.model.r, cal.model.R, geom)
    motor = np.rad2deg(cal.model.motor_residual(cal.x))
    cond = {f"L{j}": a.condition_number for j, a in cal.identifiability.items()}
    weak = [k for a in cal.identifiability.values() for k in a.weak]
    chi = np.concatenate([r.residuals for r in cal.results.values()])
    doc = {
        "source": source,
        "uncertainty": cal.uncertainty(),
        "identifiability": {
            "condition_number": max(cond.values()), "condition_number_per_limb": cond,
            "unidentifiable": cal.unidentifiable,
            "explanations": {k: pm.explain(k) for k in cal.unidentifiable},
            "weak": weak,
            "note": "condition number of the column-normalised whitened Jacobian at the solution; "
                    "unidentifiable: no first-order effect on the motor angles (held at 0); weak: "
                    "Cramer-Rao std larger than the search box half-width",
        },
        "fit": {"n_poses": int(len(motor)), "noise_sigma_mm": sigma,
                "residual_rms_sigma": float(np.sqrt(np.mean(chi**2))),
                "motor_residual_rms_deg": {f"L{j}": float(np.sqrt(np.mean(motor[:, i] ** 2)))
                                           for i, j in enumerate((1, 2))}},
        "position_map": pmap.to_dict(),
        "solver": {f"L{j}": {"n_eval": r.n_eval, "n_iter": r.n_iter, "wall_time_s": r.wall_time,
                             "success": r.success, "message": r.message} for j, r in cal.results.items()},
    }
    names = [n for r in cal.results.values() for n in r.names]
    doc["quality"] = paper_quality(len(names), [a.singular_values for a in cal.identifiability.values()])
    covs = [r.covariance for r in cal.results.values()]
    cov = block_diag(*covs) if all(c is not None for c in covs) else None
    return Calibration(params=cal.params(), model="paper", method=method, document=doc, names=names,
                       covariance=cov, residuals=chi, geometry=geom, solution=cal)


#: Orientations (phi, theta) deg over which the pointing uncertainty is predicted: phi every 30 deg,
#: theta 10..60 deg every 10 deg, and the home pose (73 orientations over the default workspace).
QUALITY_GRID = np.array([(0.0, 0.0)] + [(p, t) for t in range(10, 61, 10) for p in range(0, 360, 30)], float)


def _normal_jacobian(model, names: list[str], x: np.ndarray, ratio0: float, geom: Geometry) -> np.ndarray:
    """d normal / d parameter (N, 3, P) of the whole-chain ``model`` at ``x`` over :data:`QUALITY_GRID`."""
    phi, theta = np.deg2rad(QUALITY_GRID).T
    m = np.rad2deg(nominal_ik(phi, theta, geom))
    model.set_vector(names, x, ratio0)
    T, dT = model.predict(m, names)
    X = geom.targets[: T.shape[1]]
    n0 = platform_normals(T, X)
    h = 1e-4                                           # mm of target motion per unit step: linear regime
    scale = h / np.maximum(np.abs(dT).max(axis=(0, 1, 2)), 1e-300)
    dn = np.stack([(platform_normals(T + s * dT[..., j], X) - n0) / s for j, s in enumerate(scale)], axis=-1)
    return dn[np.isfinite(dn).all(axis=(1, 2))]


def _pointing_std_deg(dn: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """1-sigma pointing error (deg) of each grid pose: sqrt(trace(dn C dnᵀ)) of the normal's covariance."""
    return np.rad2deg(np.sqrt(np.einsum("nap,pq,naq->n", dn, cov, dn)))


def full_chain_quality(model, res, geom: Geometry) -> dict:
    """The ``quality`` object of a whole-chain fit ``res`` (``IdentResult`` with covariance, prior_std and
    effective_parameters in its ``info``) evaluated with ``model`` (the fit's forward model)."""
    names, x = list(res.names), np.asarray(res.x, float)
    ratio0 = float(res.info["stiffness_ratio"])
    dn = _normal_jacobian(model, names, x, ratio0, geom)
    post = _pointing_std_deg(dn, np.asarray(res.covariance, float))
    prior = _pointing_std_deg(dn, np.diag(np.asarray(res.info["prior_std"], float) ** 2))
    determined = int(round(float(res.info["effective_parameters"])))
    return judge(determined, len(names), float(np.sqrt(np.mean(post**2))), float(post.max()),
                 float(np.sqrt(np.mean(prior**2))), unit="deg", what="pointing")


def _record_unit(name: str) -> str:
    """A parameter's unit in a history record: mm, deg, or the log scale of the stiffness ratio."""
    return LOG_UNIT if name == LOG_RATIO else param_unit(name)


def record_document(cal, campaign_path: str | Path, machine: str = "ocpm_2dof", date: datetime | None = None) -> dict:
    """The history record of a :class:`pmcal.ocpm.calibration.Calibration` (interface units: mm, deg).

    Parameters are those of the covariance (the stiffness ratio, fitted on a log scale, is recorded
    apart); angular ones converted from rad to deg with their covariance rows and columns."""
    if cal.covariance is None:
        raise InputError("the calibration has no covariance to file", field="--history")
    names = [n for n in cal.names if n in cal.params]
    info = getattr(cal.solution, "info", None) or {}
    prior_std = {n: float(v) for n, v in (cal.document.get("prior_std") or {}).items() if n in names}
    prior_mean = {}
    values = [cal.params[n] for n in names]
    ratio = cal.document.get("stiffness_ratio")
    if LOG_RATIO in cal.names and ratio and "prior_std" in info:
        i = cal.names.index(LOG_RATIO)             # a nuisance of the test: shared, never flagged
        names.append(LOG_RATIO)
        values.append(math.log(ratio))
        prior_std[LOG_RATIO] = float(info["prior_std"][i])
        prior_mean[LOG_RATIO] = float(info["prior_mean"][i])
    idx = [cal.names.index(n) for n in names]
    scale = np.array([math.degrees(1.0) if _record_unit(n) == "deg" else 1.0 for n in names])
    cov = np.asarray(cal.covariance)[np.ix_(idx, idx)] * np.outer(scale, scale)
    fit = cal.document.get("fit", {})
    doc = make_record(machine, cal.model, cal.method, cal.document.get("frame", "base"), campaign_path, names,
                  np.array(values), cov, [_record_unit(n) for n in names], fit, fit.get("noise_sigma_mm"), date)
    doc.update(stiffness_ratio=cal.document.get("stiffness_ratio"), prior_std=prior_std, prior_mean=prior_mean)
    return doc


# ---- the calibrated model (pmcal export-model)
#: Simulation settings of the exported ocpm_2dof model, those of the dynamic twin (:mod:`pmcal.twin.ocpm.dynamics`):
#: the template's implicitfast at 1 ms diverges with stiff servos and hard closures; Euler at 0.2 ms with
#: the SS limb's axial spring locked (rigid) settles (tests/test_export_model.py)
SIMULATION_OPTIONS = {"integrator": "Euler", "timestep": "0.0002"}
#: effects an MJCF model holds, and where (``diagnose`` family names)
IN_MJCF = {"joint_compliance": "motor position servos: kp = K (N m/rad)"}


def export_parts(params_path: str) -> ExportParts:
    """ocpm_2dof's whole-chain calibration as its exported model holds it (:mod:`pmcal.export_model`): the
    geometry in the frames, nest offsets in the target sites, zero offsets as the motor joints' ``ref``, the
    closure stiffness ratio as custom numerics, the joint compliance as the servos' gain."""
    geom = default_geometry()
    cal = Calibration.load(params_path, geom)
    if cal.model != "full":
        raise InputError("the paper's per-limb model (model 'paper') is not a whole machine; export a whole-chain "
                         "calibration (pmcal identify without --model paper)", file=params_path, field="model")
    errors = ErrorSet.from_dict(cal.params, geom.n_limbs, geom.actuated)
    ratio = float(cal.document.get("stiffness_ratio") or geom.stiffness_ratio)
    m, idx = build_model(errors, geom)
    nests = (cal.document.get("nests") or {}).get("offsets_mm") or {}
    for k, site in enumerate(idx.site_targets):
        m.site_pos[site] += np.asarray(nests.get(f"t{k + 1}", [0.0, 0.0, 0.0]), float) * MM
    nominal = load_model(MODEL_XML)
    key = 0
    home_cmd = np.rad2deg(nominal.key_ctrl[key])          # the nominal home commands (the keyframe's)
    twin = Twin(errors, geom, stiffness_ratio=ratio)
    state = twin.reach(home_cmd[None])
    if not state.converged.all():
        raise RunError("the calibrated machine does not assemble at the home commands")
    qpos = state.qpos[0].copy()
    qpos[idx.qadr_base[:2]] = np.deg2rad(home_cmd)         # joint coordinate = command (ref = -dtheta)
    k_p = geom.passive_closure_stiffness / MM               # N/m
    dtheta = errors.dtheta[:2]
    edits = dict(joint_ref={"limb1_B": -dtheta[0], "limb2_B": -dtheta[1]},
                 joint_stiffness={"ss_slide": 0.0}, equality_active={"ss_axial_lock": True},
                 option=SIMULATION_OPTIONS,
                 keyframe=("home", qpos, np.deg2rad(home_cmd)),
                 custom={"pmcal_stiffness_ratio": [ratio], "pmcal_passive_closure_stiffness": [k_p],
                         "pmcal_zero_offset_deg": list(np.rad2deg(dtheta))})
    facts = {"machine": "ocpm_2dof", "model": cal.model, "stiffness_ratio": ratio,
             "zero_offsets_deg": list(np.rad2deg(dtheta)),
             "zero_offsets_as": "motor joints' ref = -dtheta: joint coordinate = commanded angle"}
    return ExportParts(MODEL_XML, MACHINE_DIR / "machine.toml", m, edits, cal.params, cal.document, facts,
                       holds=IN_MJCF, effect_edits=_servo_gains)


def _servo_gains(effects: dict) -> dict:
    """The MJCF edits of the effects ocpm_2dof's model holds: joint compliance K as the servos' kp."""
    K = effects["joint_compliance"]["value"]
    K = K if isinstance(K, list) else [K, K]
    return {"actuator_kp": {"motor1": K[0], "motor2": K[1]}}
