"""Whole-chain identification from tracker data (registration, nests, blocked targets, outliers) for
:func:`pmcal.identify` and ``pmcal identify --frame ...``: options checked at the edge, the fit chosen by
frame, and its part of the params JSON.

Units at the interface: mm and degrees. See docs/tracker_frame.md.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from pmcal.mechanism.ocpm.data import Measurements
from pmcal.calib.ocpm.fullchain import FullChainOptions, Priors, UnassembledError, identify_full
from pmcal.calib.ocpm.registration import FRAME_KEYS, read_registration
from pmcal.calib.ocpm.tracker_fit import BadCampaignError, TrackerOptions, identify_tracker
from pmcal import progress
from pmcal.errors import InputError
from pmcal.fileio import read_json

FRAMES = ("base", "tracker")
#: Robust residual scale (in tracker sigmas) beyond which the diagnosis' registration calls the campaign
#: bad: far above the identification's 5, since an unmodelled effect of a few sigma is the diagnosis' subject.
DIAGNOSIS_SCALE_RATIO = 30.0


def parse_frame(text: str | None) -> tuple[str, tuple[np.ndarray, np.ndarray] | None]:
    """``--frame base|tracker|tracker:T.json`` -> (frame, start registration or None)."""
    text = text or "base"
    frame, _, path = text.partition(":")
    if frame not in FRAMES or (path and frame != "tracker"):
        raise InputError(f"unknown frame '{text}' (base, tracker or tracker:T.json)", field="--frame")
    if not path:
        return frame, None
    doc = read_json(path, field="--frame")
    if isinstance(doc, dict) and isinstance(doc.get("registration"), dict):
        doc = doc["registration"]                      # a params JSON of an earlier tracker-frame fit
    try:
        return frame, read_registration(doc if isinstance(doc, dict) else {})
    except ValueError as exc:
        raise InputError(str(exc), file=path) from None


def check_nest_tolerance(mm: float | None) -> float:
    mm = 0.5 if mm is None else mm
    if not (np.isfinite(mm) and mm > 0):
        raise InputError(f"nest tolerance must be a positive number of mm, got {mm}", field="--nest-tolerance")
    return float(mm)


def identify_result(meas: Measurements, model, sigma: float, frame: str = "base",
                    registration0=None, nest_std_mm: float = 0.5, robust: bool | None = None,
                    fit_stiffness_ratio: bool = True, source: str | None = None):
    """The whole-chain fit for a frame: today's ``identify_full`` for a clean base-frame file, the
    registered / robust fit otherwise. A bad campaign is an :class:`InputError` naming the file."""
    opt = FullChainOptions(fit_stiffness_ratio=fit_stiffness_ratio, sigma_mm=sigma)
    blocked = not meas.visible.all()
    robust = frame == "tracker" or blocked if robust is None else robust
    if frame == "base" and not blocked and not robust:
        return identify_full(meas, model, opt)
    topt = TrackerOptions(frame=frame, registration0=registration0, nest_std_mm=nest_std_mm,
                          fit_nests=frame == "tracker", robust=robust)
    try:
        return identify_tracker(meas, model, opt, topt)
    except (BadCampaignError, UnassembledError) as exc:
        raise InputError(str(exc), file=source) from None


def warn_rejected(doc: dict) -> None:
    """One warning line on stderr per rejected target of a robust fit (``doc["rejected"]``; shown piped
    too, unless --quiet: docs/formats.md)."""
    for r in doc.get("rejected", []):
        progress.warning(f"rejected outlier: row {r['row']} ({r['pose_id']}) target t{r['target']}, "
                         f"residual {r['residual_mm']:.3g} mm")


def tracker_document(res, meas: Measurements) -> dict:
    """The registration, nests and rejected rows of a fit, for the params JSON (mm, deg)."""
    info = res.info
    doc: dict = {"frame": info.get("frame", "base")}
    if "rejected" in info:
        doc["rejected"] = info["rejected"]
        doc["rejected_rows"] = sorted({r["row"] for r in info["rejected"]})
        doc["blocked_targets"] = [{"row": int(i) + 1, "pose_id": meas.pose_id[i], "target": int(k) + 1}
                                  for i, k in np.argwhere(~meas.visible)]
    if "registration" in info:
        reg = info["registration"]
        doc["registration"] = {
            "R": reg["R"].tolist(), "t_mm": reg["t_mm"].tolist(), "rotvec_deg": reg["rotvec_deg"].tolist(),
            "std_rot_deg": reg["std_rot_deg"].tolist(), "std_t_mm": reg["std_t_mm"].tolist(),
            "meaning": "pose of the machine's base frame (motor axes) in the tracker frame: a base-frame "
                       "point p is measured at R p + t; std_rot_deg: small rotations about the tracker axes"}
        doc["gauge"] = {"held_at_zero": info["gauge_fixed"],
                        "meaning": "the base frame is fixed to the motor axes (docs/tracker_frame.md)"}
    if "nests" in info:
        n = info["nests"]
        doc["nests"] = {
            "offsets_mm": {f"t{k + 1}": n["offsets_mm"][k].tolist() for k in range(len(n["offsets_mm"]))},
            "std_mm": {f"t{k + 1}": n["std_mm"][k].tolist() for k in range(len(n["std_mm"]))},
            "prior_std_mm": n["prior_std_mm"],
            "meaning": "nest offsets from the drawing in platform coordinates, shape part only (their rigid "
                       "part is platform geometry: SS.dc*, L*.da*, L*.dmu/dnu); compensation does not use them"}
    return doc


def register_for_diagnosis(meas: Measurements, model, sigma: float, baseline_keys: list[str],
                           fit_stiffness_ratio: bool = True, registration0=None, nest_std_mm: float = 0.5,
                           source: str | None = None) -> tuple[Measurements, dict, list[str]]:
    """Tracker-frame data brought into the base frame for ``pmcal diagnose`` (docs/tracker_frame.md).

    The registration, the nest offsets and the outliers come from the robust tracker-frame fit with the
    diagnosis' own baseline (``baseline_keys``: limbs 1-2 and SS; the passive limbs held nominal fix the
    base frame's rotation, so no motor-axis angle is held); the measured targets are then carried into
    that base frame (``R^T (y - t)``) and moved from the nests to the drawing coordinates
    (``- R_p,i d_k``, ``R_p,i`` the row's platform orientation from its measured targets). The baseline
    at the fit is a point of the base-frame problem with the same residuals, so nothing the diagnosis
    looks for is lost. The diagnosis takes complete rows: a row with a blocked or a rejected target is
    left out, and named. Returns (complete base-frame rows, the frame part of the JSON, notes).
    """
    from pmcal.calib.ocpm.registration import inverse
    from pmcal.mechanism.ocpm.effects import approach_from_order
    from pmcal.mechanism.rigid import fit_pose

    opt = FullChainOptions(keys=list(baseline_keys), fit_stiffness_ratio=fit_stiffness_ratio, sigma_mm=sigma)
    # the effect the diagnosis looks for is in these residuals: a residual scale of a few sigma is what it
    # is there to explain, not a bad campaign (outliers are still rejected at 6 robust sigmas)
    # a pose the registration's model cannot assemble (at the edge of the workspace, the fit moving the
    # baseline with an effect still unmodelled) is left out of the registration and named; the
    # diagnosis, which handles such poses itself, keeps it
    topt = TrackerOptions(frame="tracker", registration0=registration0, nest_std_mm=nest_std_mm, gauge=(),
                          max_scale_ratio=DIAGNOSIS_SCALE_RATIO, leave_out_unassembled=True)
    try:
        res = identify_tracker(meas, model, opt, topt)
    except (BadCampaignError, UnassembledError) as exc:
        raise InputError(str(exc), file=source) from None
    doc = tracker_document(res, meas)
    doc["gauge"] = {"held_at_zero": [], "meaning": "the diagnosis baseline's base frame: the passive limbs "
                    "(not in the baseline) are nominal in it; fitted keys: " + ", ".join(res.names)}
    notes: list[str] = []
    lost = [r for r in res.info["unassembled"] if r["at"] == "fit"]
    outside = [r["row"] - 1 for r in res.info["unassembled"] if r["at"] == "start"]
    if lost:
        doc["registration_left_out"] = [{"row": r["row"], "pose_id": r["pose_id"], "why": "the model cannot "
                                         "assemble it at the registration's parameters"} for r in lost]
        notes.append(f"{len(lost)} row(s) left out of the registration only (the model cannot assemble "
                     "them there; kept in the diagnosis): rows " + ", ".join(str(r["row"]) for r in lost))
    if meas.approach is None and len(meas) > 1:       # the order is the full campaign's: infer it here
        meas = replace(meas, approach=approach_from_order(meas.m_cmd_deg))
        first = [0]
        notes.append("approach inferred from the row order of the whole campaign before rows were left out; "
                     "the first row, whose approach is unknown, is left out")
    else:
        first = []
    reg, nests = res.info["registration"], res.info["nests"]["offsets_mm"]
    y = inverse(reg["R"], reg["t_mm"], meas.targets)
    drop = ~meas.visible.all(axis=1)
    for r in res.info["rejected"]:
        drop[r["row"] - 1] = True
    drop[outside] = True
    X = model.geom.targets[: y.shape[1]]
    keep = np.flatnonzero(~drop)
    keep = keep[~np.isin(keep, first)]
    _, Rp, _ = fit_pose(y[keep], X + nests)
    y[keep] = y[keep] - np.einsum("nij,kj->nki", Rp, nests)
    out = replace(meas, targets=y).subset(keep)
    left = sorted(set(np.flatnonzero(drop).tolist()))
    if left:
        notes.append(f"{len(left)} row(s) left out (blocked or rejected target, or outside the workspace): "
                     "rows " + ", ".join(str(i + 1) for i in left))
    rejected = {r["row"] - 1 for r in res.info["rejected"]}
    doc["rows_left_out"] = [{"row": i + 1, "pose_id": meas.pose_id[i],
                             "why": "rejected outlier" if i in rejected else
                             "the nominal model cannot assemble it (outside the workspace?)" if i in outside
                             else "blocked target"} for i in left]
    return out, doc, notes


class _FramePriors(Priors):
    """The diagnosis' priors plus those of the base-frame correction (:data:`FRAME_PRIOR`)."""

    def std(self, key: str) -> float:
        if key in FRAME_KEYS:
            return FRAME_PRIOR[0] if FRAME_KEYS.index(key) < 3 else FRAME_PRIOR[1]
        return super().std(key)


#: Prior std of the base-frame correction the diagnosis fits after a registration (rad, mm): several
#: times what an unmodelled effect moved the registration in the tests (0.04 deg).
FRAME_PRIOR = (np.deg2rad(0.2), 2.0)


def with_frame_correction(options):
    """Diagnosis options whose baseline also carries the base-frame correction :data:`FRAME_KEYS`
    (fitted with every candidate effect: the registration is part of the baseline)."""
    from dataclasses import fields

    pri = _FramePriors(**{f.name: getattr(options.priors, f.name) for f in fields(options.priors)})
    return replace(options, baseline_keys=list(options.baseline_keys) + list(FRAME_KEYS), priors=pri)


def final_registration(doc: dict, res) -> dict:
    """The frame part of a diagnosis JSON with the registration the diagnosis ends with: the first one
    (``doc["registration"]``, kept as ``registration_before_effects``) composed with the base-frame
    correction of the final fit ``res`` (:data:`FRAME_KEYS`): ``R = R1 dR``, ``t = R1 dt + t1``; standard
    deviations from the final fit, about the tracker axes."""
    from scipy.spatial.transform import Rotation

    idx = [res.names.index(k) for k in FRAME_KEYS]
    v, C = np.asarray(res.x)[idx], np.asarray(res.covariance)[np.ix_(idx, idx)]
    first = doc["registration"]
    R1, t1 = np.asarray(first["R"]), np.asarray(first["t_mm"])
    R = R1 @ Rotation.from_rotvec(v[:3]).as_matrix()
    t = R1 @ v[3:] + t1
    Cr, Ct = R1 @ C[:3, :3] @ R1.T, R1 @ C[3:, 3:] @ R1.T
    out = dict(doc, registration_before_effects=first)
    out["registration"] = dict(first, R=R.tolist(), t_mm=t.tolist(),
                               rotvec_deg=np.rad2deg(Rotation.from_matrix(R).as_rotvec()).tolist(),
                               std_rot_deg=np.rad2deg(np.sqrt(np.diag(Cr))).tolist(),
                               std_t_mm=np.sqrt(np.diag(Ct)).tolist())
    return out
