"""Whole-chain identification from tracker data (registration, nests, blocked targets, outliers) for
:func:`pmcal.identify` and ``pmcal identify --frame ...``: options checked at the edge, the fit chosen by
frame, and its part of the params JSON.

Units at the interface: mm and degrees. See docs/tracker_frame.md.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from pmcal.mechanism.ocpm.data import Measurements
from pmcal.calib.ocpm.fullchain import FullChainOptions, identify_full
from pmcal.calib.ocpm.registration import read_registration
from pmcal.calib.ocpm.tracker_fit import BadCampaignError, TrackerOptions, identify_tracker
from pmcal.errors import InputError

FRAMES = ("base", "tracker")


def parse_frame(text: str | None) -> tuple[str, tuple[np.ndarray, np.ndarray] | None]:
    """``--frame base|tracker|tracker:T.json`` -> (frame, start registration or None)."""
    text = text or "base"
    frame, _, path = text.partition(":")
    if frame not in FRAMES or (path and frame != "tracker"):
        raise InputError(f"unknown frame '{text}' (base, tracker or tracker:T.json)", field="--frame")
    if not path:
        return frame, None
    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError("file not found", file=path, field="--frame") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"cannot read the registration ({exc})", file=path) from None
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
    except BadCampaignError as exc:
        raise InputError(str(exc), file=source) from None


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
