"""A calibration of the planar 2-DOF robot (``planar_2dof``, Mei et al. 2017): the same calls as every other
machine's (``pmcal.identify`` -> ``cal.setpoints`` -> ``cal.save``), the command line a thin layer over it.

Models: ``"simplified"`` (the paper's 4 parameters, default), ``"full"`` (all 12, rank 9) by the paper's
linear identification (eq. 25/29: ``method`` tsvd, ls or gls), or ``"chain"`` (the 12 errors on the
generic closed-chain core: exact model, generalised least squares with the servo and scale noise, Tikhonov
prior, base set from the data). Units: mm and degrees (docs/planar_measurement_format.md); the task is the
platform position ``x_mm, y_mm`` in the seed frame (y < 0 below the base); commands ``theta1, theta2`` deg.

Example
-------
>>> import pmcal                                                              # doctest: +SKIP
>>> machine = pmcal.Machine.builtin("planar_2dof")                            # doctest: +SKIP
>>> cal = pmcal.identify(pmcal.read_measurements("m.csv", machine))           # doctest: +SKIP
>>> cal.setpoints([[0.0, -300.0]])                                            # doctest: +SKIP
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pmcal.calib.closed_chain import compensate_targets, identify_chain, reading_covariance
from pmcal.calib.planar.identification import METHODS, MODELS, system
from pmcal.calib.planar.identification import identify as identify_linear
from pmcal.calibration_document import CalibrationDocument
from pmcal.campaign_quality import judge
from pmcal.errors import InputError
from pmcal.export_model import ExportParts, frame_parts
from pmcal.planar.io import MECHANISM, PlanarMeasurements, params_document, read_params
from pmcal.mechanism.machine_spec import MachineSpec
from pmcal.mechanism.planar.chain import PlanarChainModel
from pmcal.mechanism.planar.geometry import ERROR_KEYS, Errors, interface_unit
from pmcal.mechanism.planar.noise import Noise
from pmcal.mjcf import machine_dir
from pmcal.twin.planar.config import MODEL_XML as PLANAR_XML, PlanarMachine, default_machine
from pmcal.twin.planar.twin import PlanarTwin

#: ``model=`` values and the model each names
MODEL_CHOICES = {None: "simplified", "paper": "simplified", "simplified": "simplified", "full": "full",
                 "chain": "chain"}


def noise_of(machine: PlanarMachine, sigma: float | None) -> Noise:
    """The measurement noise: the machine's (the paper's eq. 34), or a linear-scale sigma (mm) given."""
    if sigma is None:
        return machine.noise
    if not (math.isfinite(sigma) and sigma > 0):
        raise InputError(f"scale noise must be a positive number of mm, got {sigma}", field="--sigma")
    return Noise(scale=float(sigma), servo=machine.noise.servo)


def chain_model(machine: PlanarMachine) -> PlanarChainModel:
    """The generic core's model of this machine: ``mjcf/planar_2dof/chain`` through the paper's closed forms
    (the fast path, :class:`pmcal.mechanism.planar.chain.PlanarChainModel`)."""
    return PlanarChainModel(MachineSpec.load(machine_dir("planar_2dof") / "chain"), machine.geometry)


def rank_deficiency(geom, meas: PlanarMeasurements, model: str, doc: dict) -> str:
    """Describe the null space of the identification matrix ``G`` (eq. 24/28) in ``doc`` ("null_space": one
    unit vector per missing rank, keyed by parameter, in the scaled unknowns of eq. 29: mm, and mm per
    link length for the zero offsets); return a one-line summary, or "" when ``G`` has full column rank."""
    G, _ = system(geom, meas.r, meas.readings, model, None, meas.segments)
    _, s, Vt = np.linalg.svd(G)
    rank = int(doc.get("rank") or 0)
    n = G.shape[1]
    if rank >= n:
        return ""
    keys = list(MODELS[model])
    null = [{k: round(float(v), 6) for k, v in zip(keys, vec) if abs(v) > 1e-6} for vec in Vt[rank:]]
    doc["null_space"] = null
    biggest = [max(vec, key=lambda k: abs(vec[k])) for vec in null]
    return (f"rank {rank} of {n}: the readings cannot tell {n - rank} combination(s) of the parameters "
            f"apart (largest in {', '.join(dict.fromkeys(biggest))})")


@dataclass
class PlanarCalibration(CalibrationDocument):
    """The identified planar robot: its parameters document and what the identification found.

    Attributes
    ----------
    document : dict
        The parameters JSON (docs/planar_measurement_format.md): ``params`` (mm, deg), ``units``, ``model``,
        ``method``, rank, uncertainty, ``quality``; ``success`` false for a rank-deficient fit not accepted.
    deficient : str
        Why the fit is rank deficient ("" when it is not): the combinations the readings cannot separate.
    path : str
        The file it was loaded from ("" when identified here): what a refusal names.
    """

    document: dict
    deficient: str = ""
    path: str = ""

    def setpoints(self, targets, *, force: bool = False) -> np.ndarray:
        """Motor commands (n, 2) deg that bring the identified machine's platform to ``targets`` (n, 2):
        ``x_mm, y_mm`` in the seed frame (the identified machine's inverse kinematics, the zero offsets taken
        off). InputError for a calibration flagged not usable (unless ``force``) or a target out of reach."""
        errors = Errors.from_interface(self.params)
        self.refuse_unusable(force, MECHANISM,
                             f"measure at least {2 * len(errors.as_internal())} positions spread over the workspace "
                             "('pmcal --machine planar_2dof twin measure --poses 24')")
        r = np.atleast_2d(np.asarray(targets, float))
        if r.ndim != 2 or r.shape[1] != 2:
            raise InputError(f"targets need 2 columns (x_mm, y_mm), got shape {r.shape}", field="targets")
        commands = compensate_targets(chain_model(default_machine()), errors.as_interface(), r)
        bad = ~np.all(np.isfinite(commands), axis=1)
        if np.any(bad):
            raise InputError("out of reach of the identified machine (or outside a motor's range)",
                             row=int(np.flatnonzero(bad)[0]) + 1, field="y_mm")
        return commands

    def compensation_table(self, *args, **kwargs):
        """planar_2dof has no PLC table (offline compensation of target lists only): InputError."""
        raise InputError("compensation tables are not available for planar_2dof", field="--table")

    @classmethod
    def load(cls, path: str | Path) -> PlanarCalibration:
        """Read a planar parameters JSON (checked: mechanism, keys, value sizes)."""
        _, doc = read_params(path)
        return cls(doc, path=str(path))


def identify(meas: PlanarMeasurements, *, model: str | None = None, method: str | None = None,
             sigma: float | None = None, allow_rank_deficient: bool = False) -> PlanarCalibration:
    """Identify the planar robot's errors from a measurement campaign.

    Parameters
    ----------
    meas : PlanarMeasurements
        From :func:`pmcal.planar.io.read_measurements` (or ``pmcal.read_measurements(path, machine)``).
    model : {"simplified", "paper", "full", "chain"}, optional
        The error model (default the paper's 4 parameters).
    method : {"tsvd", "ls", "gls"}, optional
        The linear identification's method (default the machine's, eq. 29); not for ``model="chain"``.
    sigma : float, optional
        Linear-scale noise, mm (default the paper's eq. 34).
    allow_rank_deficient : bool
        Accept a rank-deficient fit (the minimum-norm solution); otherwise its document says ``success``
        false and :attr:`PlanarCalibration.deficient` why.

    Returns
    -------
    PlanarCalibration
    """
    machine = default_machine()
    chosen = MODEL_CHOICES.get(model)
    if chosen is None:
        raise InputError(f"unknown model '{model}' (simplified/paper, full or chain)", field="--model")
    noise = noise_of(machine, sigma)
    if chosen == "chain":
        return PlanarCalibration(_chain_document(machine, meas, method, noise))
    method = method or machine.calibration.method
    if method not in METHODS:
        raise InputError(f"unknown method '{method}' for planar_2dof ({', '.join(METHODS)})", field="--method")
    n_unknowns = 4 if chosen == "simplified" else 12
    if len(meas.readings) < n_unknowns:
        raise InputError(f"{len(meas.readings)} readings for {n_unknowns} unknowns of the {chosen} model",
                         file=meas.path, field="scale_change_mm")
    res = identify_linear(machine.geometry, meas.r, meas.readings, model=chosen, method=method,
                          segments=meas.segments, noise=noise)
    doc = params_document(res, {"n_positions": len(meas.ids), "source": str(meas.path),
                                "noise": {"scale_sigma_mm": noise.scale,
                                          "servo_sigma_deg": math.degrees(noise.servo)}})
    doc["quality"] = judge(int(doc.get("rank") or 0), len(doc["params"]), what="position", unit="mm")
    deficient = rank_deficiency(machine.geometry, meas, chosen, doc)
    if deficient and not allow_rank_deficient:
        doc["success"] = False
        doc["message"] = (f"{deficient}; the parameters along the null space are not identified (values and "
                          "uncertainties hold only for the identifiable combinations). --allow-rank-deficient "
                          "accepts the minimum-norm solution")
    return PlanarCalibration(doc, deficient if not allow_rank_deficient else "")


def _chain_document(machine: PlanarMachine, meas: PlanarMeasurements, method: str | None, noise: Noise) -> dict:
    """``model="chain"``: the paper's 12 errors on the generic closed-chain core through the closed-form fast
    path (the same numbers as the MuJoCo twin of ``mjcf/planar_2dof/chain`` to 1e-9,
    tests/test_planar_chain_model.py): the base set found from the data, the combinations it cannot separate
    written out (``unidentifiable``)."""
    if method:
        raise InputError("--model chain fits by least squares on the exact model (no --method)", field="--method")
    model = chain_model(machine)
    cmd = np.rad2deg(meas.theta_cmd)
    servo = [math.degrees(noise.servo)] * 2
    cov = reading_covariance(model, cmd, servo, noise.scale, meas.segments)
    try:
        res = identify_chain(model, cmd, meas.readings, noise.scale, keys=list(ERROR_KEYS), segments=meas.segments,
                             covariance=cov)
    except ValueError as exc:
        raise InputError(str(exc), file=meas.path) from None
    return {"mechanism": MECHANISM, "model": "chain", "method": "lm+tikhonov (generic closed-chain core)",
            "params": {k: float(res.params[k]) for k in ERROR_KEYS},
            "units": {k: interface_unit(k) for k in ERROR_KEYS}, "identifiable": list(res.base),
            "uncertainty": dict(res.std), "crlb": dict(res.crlb), "combinations": dict(res.combinations),
            "unidentifiable": list(res.unidentifiable), "weak": list(res.weak), "rank": int(res.rank),
            "condition_number": float(res.condition_number), "residual_rms_mm": float(res.residual_rms_mm),
            "chi2_per_dof": float(res.chi2_per_dof), "n_readings": int(len(meas.readings)),
            "n_positions": len(meas.ids), "source": str(meas.path), "success": bool(res.success),
            "message": res.message, "noise": {"scale_sigma_mm": noise.scale, "servo_sigma_deg": servo[0]}}


def export_parts(params_path: str) -> ExportParts:
    """The planar robot's calibration: its paper-named errors (``io_planar``) mapped onto the frame errors of
    ``mjcf/planar_2dof/chain`` (``[names]``), exported as a machine folder's (:func:`_frames`)."""
    errors, doc = read_params(params_path)
    planar = PlanarTwin(errors, default_machine())
    m, edits = frame_parts(planar.chain, planar.chain.spec, planar.params)
    facts = {"machine": "planar_2dof", "model": doc.get("model") or "",       # "model": null is accepted
             "zero_offsets_deg": list(np.rad2deg(errors.dtheta)),
             "zero_offsets_as": "motor joints' ref = -dtheta: joint coordinate = commanded angle"}
    return ExportParts(PLANAR_XML, PLANAR_XML.parent / "machine.toml", m, edits, doc.get("params", {}), doc, facts)
