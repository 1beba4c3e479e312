"""File formats of the over-constrained PM (docs/formats.md): measurements, parameters, targets, setpoints.

Validation happens here, at the edge: one :class:`InputError` naming file, row and field.
"""

from __future__ import annotations

import difflib
import math
import re
from pathlib import Path

import numpy as np

from pmcal import progress
from pmcal.mechanism.ocpm.config import Geometry, default_geometry
from pmcal.mechanism.ocpm.data import Measurements
from pmcal.mechanism.ocpm.kinematics import nominal_fk, nominal_pose
from pmcal.mechanism.ocpm.params import ANGULAR_FIELDS, PAPER_LIMB_FIELDS, check_key
from pmcal.mechanism.rotations import pointing_error, tilt_torsion
from pmcal.csvio import (LONG_POSES, MAX_POSES, PLAUSIBLE_TARGET_DISTANCE_MM,  # noqa: F401
                         PLAUSIBLE_TARGET_DISTANCE_TRACKER_MM, check_blocked, check_context, check_nest_distances,
                         check_time_order, read_csv, target_columns, write_columns, write_csv)
from pmcal.errors import InputError
from pmcal.fileio import check_param_values, read_json, read_text, write_json
from pmcal.io_tracker import (BASE_FRAME_LIMITS, BASE_FRAME_NAMES, ControllerLog, ImportResult, TrackerExport,  # noqa: F401
                              named_base_frame, place_points)

MECHANISM = "ocpm_2dof"

#: Largest disagreement between the measured tilt and the tilt the commands give on the nominal machine
#: that is still plausible for a machine with geometric errors (deg). Beyond it, a unit mix-up is likely.
PLAUSIBLE_POINTING_DEG = 5.0
#: Largest target coordinate a measurement file may hold, mm (100 m: beyond any laser tracker's range).
MAX_COORDINATE_MM = 1e5
#: Largest azimuth a targets file or motor command a measurement file may give, deg (either sign): one turn;
#: beyond it a value is a unit or typing error, not an orientation.
PHI_LIMIT_DEG = 360.0


def read_measurements(path: str | Path, geom: Geometry | None = None, check_units: bool = True,
                      frame: str = "base") -> Measurements:
    """Read and validate a measurement CSV (docs/formats.md): missing columns, non-numbers, NaN, duplicate
    ids, targets inconsistent with the platform (metres?), commands outside the workspace or
    disagreeing with the measured tilt (radians?).

    A blocked target has all three cells empty (NaN in :class:`Measurements`); a half-empty target or a
    row with fewer than two targets is an error naming row and field. ``frame="tracker"``: the targets
    are in the tracker's own frame, so only frame-free checks (distances between targets) apply."""
    geom = geom or default_geometry()
    t = read_csv(path, max_rows=MAX_POSES)
    k = 3
    while t.has(f"t{k + 1}_x"):
        k += 1
    if k > len(geom.targets):
        raise InputError(f"target t{k} has no platform coordinates in the machine configuration",
                         file=t.path, field=f"t{k}_x")
    t.require(["pose_id", "m1_cmd_deg", "m2_cmd_deg"] + target_columns(k))
    _check_other_columns(t, ["pose_id", "m1_cmd_deg", "m2_cmd_deg"] + target_columns(k) + list(OPTIONAL_COLUMNS))
    ids = t.unique_ids("pose_id")
    m = np.stack([t.numbers("m1_cmd_deg"), t.numbers("m2_cmd_deg")], axis=1)
    flat = np.stack([t.numbers(c, allow_empty=True) for c in target_columns(k)], axis=1)
    for i, j in np.argwhere(np.abs(flat) > MAX_COORDINATE_MM)[:1]:
        raise InputError(f"{flat[i, j]:g} mm is not a target coordinate (at most {MAX_COORDINATE_MM:g} mm from the "
                         "frame's origin)", file=t.path, row=int(i) + 1, field=target_columns(k)[j])
    coords = flat.reshape(len(ids), k, 3)
    check_blocked(coords, t.path)
    optional = {c: (t.numbers(c, allow_empty=True, default=d) if t.has(c) else None)
                for c, d in (("temp_c", math.nan), ("time_s", math.nan), ("payload_kg", 0.0))}
    check_context(t.path, payload_kg=optional["payload_kg"])
    approach = None
    if t.has("m1_approach") and t.has("m2_approach"):
        approach = np.stack([t.numbers("m1_approach"), t.numbers("m2_approach")], axis=1)
    meas = Measurements(pose_id=ids, m_cmd_deg=m, targets=coords, approach=approach, **optional)
    if check_units:
        check_plausible(meas, geom, t.path, frame)
    return meas


#: optional columns of a measurement file (docs/formats.md)
OPTIONAL_COLUMNS = ("temp_c", "time_s", "payload_kg", "m1_approach", "m2_approach")


def _check_other_columns(t, known: list[str]) -> None:
    """A column the machine does not read: a motor beyond m2 or a target beyond the platform's means another
    machine's file; a near-miss of a known column (``temp_C``, ``time_sec``) is refused naming the column
    meant (it would be ignored and its data lost); any other column is ignored with a warning."""
    for c in t.header:
        if c in known:
            continue
        if re.fullmatch(r"m\d+_cmd_(deg|mm)", c):
            raise InputError("ocpm_2dof has 2 motors (m1_cmd_deg, m2_cmd_deg): this is another machine's file "
                             "(give its --machine)", file=t.path, field=c)
        close = difflib.get_close_matches(c.lower(), known, n=1, cutoff=0.75)
        if close:
            raise InputError(f"unknown column; did you mean {close[0]}? (column names are case-sensitive; this one "
                             "would be ignored)", file=t.path, field=c)
        progress.warning(f"{t.path}: column {c} is not read by ocpm_2dof (ignored)")


def read_campaign_context(path: str | Path) -> dict[str, np.ndarray]:
    """The campaign context a targets file may carry besides the orientations, in its row order (the
    columns ``pmcal twin plan --for-diagnosis`` writes): ``payload_kg`` (kg, >= 0), ``time_s`` (s, not
    decreasing), ``temp_c`` (degC; a plan's ``temp_c_planned`` when there is no ``temp_c``), ``approach``
    (N, 2) from ``m1_approach``, ``m2_approach`` (+1 / -1). Only the columns present."""
    t = read_csv(path)
    out: dict[str, np.ndarray] = {}
    if t.has("payload_kg"):
        out["payload_kg"] = t.numbers("payload_kg")
    if t.has("time_s"):
        out["time_s"] = t.numbers("time_s")
        check_time_order(out["time_s"], t.path)
    temp_field = next((c for c in ("temp_c", "temp_c_planned") if t.has(c)), None)
    if temp_field:
        out["temp_c"] = t.numbers(temp_field)
    if t.has("m1_approach") and t.has("m2_approach"):
        out["approach"] = np.stack([t.numbers("m1_approach"), t.numbers("m2_approach")], axis=1)
    check_context(t.path, out.get("approach"), out.get("temp_c"), temp_field or "temp_c", out.get("payload_kg"))
    return out


def check_commands(m_cmd_deg: np.ndarray, path: str) -> None:
    """Motor commands (rows of a file, deg) within +-PHI_LIMIT_DEG: anything else is not an angle (was a
    LinAlgError in the forward kinematics)."""
    for i, j in np.argwhere(np.abs(m_cmd_deg) > PHI_LIMIT_DEG)[:1]:
        raise InputError(f"command {m_cmd_deg[i, j]:g} deg is outside -{PHI_LIMIT_DEG:g}..{PHI_LIMIT_DEG:g} "
                         "deg", file=path, row=int(i) + 1, field=f"m{j + 1}_cmd_deg")


def check_plausible(meas: Measurements, geom: Geometry, path: str, frame: str = "base") -> None:
    """Catch unit mix-ups and impossible rows with a message naming the row and field (blocked targets
    skipped; in the tracker frame only the distances between targets are checked)."""
    limit = PLAUSIBLE_TARGET_DISTANCE_MM if frame == "base" else PLAUSIBLE_TARGET_DISTANCE_TRACKER_MM
    check_nest_distances(meas.targets, geom.targets[: meas.targets.shape[1]], path, limit)
    check_commands(meas.m_cmd_deg, path)
    beta = np.deg2rad(meas.m_cmd_deg)
    phi, theta = nominal_fk(beta, geom)
    _, R_meas, _ = meas.poses(geom)
    for i in np.flatnonzero(~np.isfinite(theta)):
        hint = ""
        as_rad = np.rad2deg(beta[i])
        if np.all(np.isfinite(nominal_fk(np.deg2rad(as_rad)[None], geom)[1])):
            hint = " (values look like radians: the file must be in degrees)"
        raise InputError(f"commands ({meas.m_cmd_deg[i, 0]:.6g}, {meas.m_cmd_deg[i, 1]:.6g}) deg are outside "
                         f"the workspace of the machine{hint}", file=path, row=int(i) + 1, field="m1_cmd_deg")
    if frame != "base":
        return
    ok = np.isfinite(R_meas).all(axis=(1, 2))
    err = np.zeros(len(meas))
    err[ok] = np.rad2deg(pointing_error(tilt_torsion(phi[ok], theta[ok]), R_meas[ok]))
    off = np.flatnonzero(err > PLAUSIBLE_POINTING_DEG)
    if off.size > 0.5 * ok.sum() and not _fits_as_radians(meas, R_meas, ok, geom):
        # most rows off, the targets consistent with the platform, the commands not radians: a frame
        raise InputError(f"the measured platform points {np.median(err[off]):.3g} deg (median of {off.size} of "
                         f"{len(meas)} rows) away from where the commands put a nominal machine, its targets "
                         "consistent: the targets look like they are in the tracker's own frame: identify with "
                         "--frame tracker (docs/tracker_frame.md)", file=path, row=int(off[0]) + 1, field="t1_x")
    for i in off:
        raise InputError(f"the measured platform points {err[i]:.3g} deg away from where the commands put a "
                         f"nominal machine (limit {PLAUSIBLE_POINTING_DEG} deg): wrong units (radians?) or a "
                         "mislabelled row", file=path, row=int(i) + 1, field="m1_cmd_deg")


def _fits_as_radians(meas: Measurements, R_meas: np.ndarray, ok: np.ndarray, geom: Geometry) -> bool:
    """Whether the commands, read as radians, point the nominal machine where the platform was measured."""
    phi, theta = nominal_fk(np.asarray(meas.m_cmd_deg, float)[ok], geom)
    good = np.isfinite(theta)
    if not good.any():
        return False
    err = np.rad2deg(pointing_error(tilt_torsion(phi[good], theta[good]), R_meas[ok][good]))
    return bool(np.median(err) <= PLAUSIBLE_POINTING_DEG)


def write_measurements(path: str | Path, meas: Measurements, comments=()) -> None:
    """Write a measurement CSV (docs/formats.md), atomically; optional columns only when present."""
    k = meas.targets.shape[1]
    m = np.asarray(meas.m_cmd_deg)
    cols = [("m1_cmd_deg", m[:, 0], "{:.6f}"), ("m2_cmd_deg", m[:, 1], "{:.6f}")]
    cols += [(c, meas.targets[:, i // 3, i % 3], "{:.5f}") for i, c in enumerate(target_columns(k))]
    for name, arr, fmt in (("temp_c", meas.temp_c, "{:.3f}"), ("time_s", meas.time_s, "{:.2f}"),
                           ("payload_kg", meas.payload_kg, "{:.3f}")):
        if arr is not None:
            cols.append((name, np.asarray(arr), fmt))
    if meas.approach is not None:
        cols += [("m1_approach", meas.approach[:, 0], "{:+.0f}"), ("m2_approach", meas.approach[:, 1], "{:+.0f}")]
    write_columns(path, "pose_id", meas.pose_id, cols, comments)


#: The parameters file's schema (docs/formats.md): error models, and the largest plausible magnitude of a
#: geometric error. Beyond it a unit mix-up (radians, micrometres, angles x1000) is far more likely than a
#: machine that still closes its chain: the paper's Table 2 errors are below 2 mm and 1 deg.
PARAM_MODELS = ("full", "paper")
PLAUSIBLE_PARAM = {"mm": 25.0, "deg": 10.0}


def param_unit(key: str) -> str:
    """``deg`` for an angular parameter key, else ``mm``."""
    return "deg" if key.rsplit(".", 1)[-1] in ANGULAR_FIELDS else "mm"


def paper_keys_only(params: dict[str, float]) -> bool:
    """Every key is one of the paper's 11 per limb of limbs 1 and 2 (a paper-model file)."""
    return bool(params) and all(k.split(".", 1)[0] in ("L1", "L2") and k.split(".", 1)[1] in PAPER_LIMB_FIELDS
                                for k in params)


def read_params(path: str | Path, geom: Geometry | None = None) -> tuple[dict[str, float], dict]:
    """Read and validate a parameters JSON (docs/formats.md); returns (params in mm/deg, whole document).

    The one schema of the ``ocpm_2dof`` parameters file, whichever command reads it: ``mechanism``,
    ``model`` (one of :data:`PARAM_MODELS` when present), ``stiffness_ratio`` (a positive number when
    present), ``params`` keys (:func:`pmcal.mechanism.ocpm.params.check_key`), finite numbers within
    :data:`PLAUSIBLE_PARAM` of their unit.
    """
    geom = geom or default_geometry()
    p = str(path)
    doc = read_json(path)
    if not isinstance(doc, dict) or not isinstance(doc.get("params", None), dict):
        raise InputError("expected an object with a 'params' object", file=p, field="params")
    mech = doc.get("mechanism", MECHANISM)
    if mech != MECHANISM:
        raise InputError(f"parameters are for mechanism '{mech}', not '{MECHANISM}'", file=p, field="mechanism")
    for key in doc["params"]:
        msg = check_key(key, geom.n_limbs, geom.actuated)
        if msg:
            raise InputError(msg, file=p, field=key)
    params = check_param_values(doc["params"], p, param_unit, PLAUSIBLE_PARAM, prefix="")
    model = doc.get("model")
    if model is not None and model not in PARAM_MODELS:
        raise InputError(f"unknown model {model!r} (known: {', '.join(PARAM_MODELS)})", file=p, field="model")
    ratio = doc.get("stiffness_ratio")
    if ratio is not None and (isinstance(ratio, bool) or not isinstance(ratio, (int, float))
                              or not math.isfinite(ratio) or ratio <= 0):
        raise InputError(f"stiffness ratio {ratio!r} is not a positive number", file=p, field="stiffness_ratio")
    return params, doc


def write_params(path: str | Path, params: dict[str, float], **extra) -> None:
    """Write a parameters JSON atomically: ``{"mechanism", "units", "params", ...extra}``."""
    doc = {"mechanism": MECHANISM, "units": {"length": "mm", "angle": "deg"},
           "params": {k: float(v) for k, v in params.items()}}
    doc.update(extra)
    write_json(path, doc)


def read_targets(path: str | Path, theta_max_deg: float = 90.0) -> tuple[np.ndarray, np.ndarray]:
    """Target orientations (``phi_deg``, ``theta_deg``) from a targets CSV."""
    t = read_csv(path)
    t.require(["phi_deg", "theta_deg"])
    phi, theta = t.numbers("phi_deg"), t.numbers("theta_deg")
    for i in np.flatnonzero(np.abs(phi) > PHI_LIMIT_DEG):
        raise InputError(f"azimuth {phi[i]:g} deg is outside -{PHI_LIMIT_DEG:g}..{PHI_LIMIT_DEG:g} deg", file=t.path,
                         row=int(i) + 1, field="phi_deg")
    for i in np.flatnonzero((theta < 0) | (theta > theta_max_deg)):
        raise InputError(f"tilt {theta[i]:g} deg is outside 0..{theta_max_deg:g} deg", file=t.path,
                         row=int(i) + 1, field="theta_deg")
    return phi, theta


def write_setpoints(path: str | Path, phi_deg, theta_deg, m_deg, comments=()) -> None:
    """Targets with the motor commands that reach them appended (``m1_deg``, ``m2_deg``)."""
    rows = ([f"{p:.6f}", f"{t:.6f}", f"{m[0]:.6f}", f"{m[1]:.6f}"] for p, t, m in zip(phi_deg, theta_deg, m_deg))
    write_csv(path, ["phi_deg", "theta_deg", "m1_deg", "m2_deg"], rows, comments)


# ---- tracker exports and controller logs joined into this machine's measurements (pmcal.io_tracker)
def join(export: TrackerExport, log: ControllerLog, names: str | None = None,
         time_tolerance_s: float | None = None, geom: Geometry | None = None) -> ImportResult:
    """Join tracker points and the controller log into ocpm_2dof measurements (mm, deg).

    Each point's name (:func:`compile_names`) gives its nest (``target`` group: ``T1``, ``T2``, ... ->
    the machine's nests 1, 2, ...) and, when the pattern has a ``pose`` group that matches, its pose:
    the pose label's digits equal those of a log ``pose_id`` (``P007`` is pose 7). Points without a pose
    in their name are joined by time: the log row nearest in time within ``time_tolerance_s`` (needs
    time stamps on both sides; two log rows within the tolerance is ambiguous).

    A point measured twice (same pose and nest; a re-shot point) keeps the **last** one, the one the
    operator took to replace the first, and says so. Unmatched and ambiguous points are left out and
    reported; a nest without a point is blocked (NaN). Poses with fewer than two points are left out.

    Raises
    ------
    pmcal.errors.InputError
        No point matches the log, or the log's pose numbers are not unique.

    Examples
    --------
    >>> res = join(read_sa_ascii("tracker.txt"), read_controller_log("log.csv"))   # doctest: +SKIP
    >>> res.meas.targets.shape                                                     # doctest: +SKIP
    (24, 3, 3)
    """
    geom = geom or default_geometry()
    check_commands(log.commands, log.path)
    placed = place_points(export, log, [f"T{k + 1}" for k in range(len(geom.targets))], names, time_tolerance_s,
                          min_points=2)
    idx = placed.keep
    meas = Measurements(pose_id=[log.pose_id[i] for i in idx], m_cmd_deg=log.commands[idx],
                        targets=placed.coords[idx], temp_c=None if log.temp_c is None else log.temp_c[idx],
                        time_s=None if log.time_s is None else log.time_s[idx])
    base, reason = in_base_frame(meas, geom, export.frame)
    return placed.result(export, log, meas, base, reason, "identify with --frame tracker")


def in_base_frame(meas: Measurements, geom: Geometry, frame_name: str | None = None) -> tuple[bool, str]:
    """Whether measured points are in the machine's base frame, and why not.

    Not in the base frame: the export names a working frame other than :data:`BASE_FRAME_NAMES` (after
    SA's ``COLLECTION::``), or the rigid check fails: the platform fitted to the points lies more than
    :data:`BASE_FRAME_LIMITS` (mm, deg) from where the commands put the nominal machine's platform."""
    base, reason = named_base_frame(frame_name)
    if not base:
        return base, reason
    r, R, _ = meas.poses(geom)
    phi, theta = nominal_fk(np.deg2rad(meas.m_cmd_deg), geom)
    ok = np.isfinite(theta) & np.isfinite(R).all(axis=(1, 2))
    if not ok.any():
        return False, "no pose to check the frame with"
    r_nom, _ = nominal_pose(phi[ok], theta[ok], geom)
    dist = np.linalg.norm(r[ok] - r_nom, axis=1)
    angle = np.rad2deg(pointing_error(tilt_torsion(phi[ok], theta[ok]), R[ok]))
    if np.median(dist) > BASE_FRAME_LIMITS[0] or np.median(angle) > BASE_FRAME_LIMITS[1]:
        return False, (f"the platform is {np.median(dist):.3g} mm and {np.median(angle):.3g} deg (median) from "
                       "where the commands put it in the base frame")
    return True, ""
