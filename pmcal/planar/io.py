"""File formats of the planar 2-DOF robot (``docs/planar_measurement_format.md``): measurements, parameters,
targets, setpoints. Validation happens here, at the edge: one :class:`InputError` naming file, row and
field; every output is written atomically. Units in files: mm and degrees.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pmcal.mechanism.planar.geometry import ERROR_KEYS, Errors, Geometry, interface_unit
from pmcal.mechanism.planar.kinematics import forward, inverse, mm_vector
from pmcal.calib.solvers.result import IdentResult
from pmcal.csvio import read_csv, write_csv
from pmcal.errors import InputError
from pmcal.fileio import check_param_values, read_json, read_text

MECHANISM = "planar_2dof"
MEAS_COLUMNS = ("pose_id", "theta1_cmd_deg", "theta2_cmd_deg", "scale_change_mm")
#: most positions a measurement file may hold: the reading covariance is dense (rows x rows)
MAX_POSITIONS = 2000
#: accepted ratio of the readings to the nominal distance changes (a geometric error changes them by
#: a few per cent; metres or micrometres change them by 1000)
PLAUSIBLE_READING_RATIO = (0.5, 2.0)
#: largest plausible |scale change| between adjacent positions, mm (the paper's scale range is 350 mm)
PLAUSIBLE_CHANGE_MM = 400.0


@dataclass
class PlanarMeasurements:
    """A measurement file (mm, rad).

    ids : pose labels. theta_cmd : (K, 2) commanded motor angles, rad. readings : (rows,) scale changes
    between adjacent positions of the same chain, mm (one per row of
    :func:`pmcal.calib.planar.identification.difference_operator`). segments : (K,) chain label of each
    position (one chain unless the file has a ``campaign`` column). r : (K, 2) the positions the nominal
    controller believes it commanded, mm.
    """

    ids: list[str]
    theta_cmd: np.ndarray
    readings: np.ndarray
    segments: np.ndarray
    r: np.ndarray
    path: str = ""
    machine: object = None          # the pmcal.Machine whose campaign this is (set by pmcal.read_measurements)


def _plausible_positions(geom: Geometry, theta: np.ndarray, path: str, fields: str) -> np.ndarray:
    """Nominal positions of commanded angles; angles off the robot's assembly mode (elbows outwards,
    platform below the base) mean wrong units or a wrong machine."""
    r = forward(geom, theta)
    with np.errstate(invalid="ignore"):
        back = inverse(geom, r)
        wrapped = np.angle(np.exp(1j * (back - theta)))
        bad = ~np.all(np.isfinite(r), axis=1) | (r[:, 1] >= 0) | np.any(~(np.abs(wrapped) < 1e-6), axis=1)
    if np.any(bad):
        row = int(np.flatnonzero(bad)[0]) + 1
        raise InputError("the commanded angles are not a pose of this robot (degrees expected: theta1 near 0, "
                         "theta2 near 180, platform below the base)", file=path, row=row, field=fields)
    return r


def _check_reading_units(geom: Geometry, r: np.ndarray, change: np.ndarray, starts: np.ndarray, path: str) -> None:
    """The readings must be the changes of the distance O1O2 in mm: compared with the nominal changes
    (eq. 4) by their least-squares ratio, which a unit mistake moves by a factor 1000."""
    length = np.linalg.norm(mm_vector(geom, r), axis=1)
    expected = np.diff(length)[~starts[1:]]
    got = change[~starts]
    scale = float(expected @ expected)
    if scale < 1.0:                               # positions too close to tell (under 1 mm of change)
        return
    ratio = float(got @ expected) / scale
    lo, hi = PLAUSIBLE_READING_RATIO
    if not lo <= ratio <= hi:
        row = int(np.flatnonzero(~starts)[int(np.argmax(np.abs(expected)))]) + 1
        hint = " (metres?)" if abs(ratio) < 0.01 else " (micrometres?)" if abs(ratio) > 100 else ""
        raise InputError(f"the readings are {ratio:.3g} times the distance changes the commanded positions give: "
                         f"the scale changes must be in mm{hint}", file=path, row=row, field="scale_change_mm")


def read_measurements(path: str | Path, geom: Geometry, min_positions: int = 6) -> PlanarMeasurements:
    """Read and validate a planar measurement CSV."""
    t = read_csv(path, max_rows=MAX_POSITIONS)
    t.require(MEAS_COLUMNS)
    ids = t.unique_ids("pose_id")
    theta = np.deg2rad(np.stack([t.numbers("theta1_cmd_deg"), t.numbers("theta2_cmd_deg")], axis=1))
    change = t.numbers("scale_change_mm", allow_empty=True)
    if t.has("campaign"):
        labels = t.text("campaign")
        for i, v in enumerate(labels):
            if v == "":
                raise InputError("empty campaign label", file=t.path, row=i + 1, field="campaign")
        seg = np.cumsum([True] + [labels[i] != labels[i - 1] for i in range(1, len(labels))])
    else:
        seg = np.ones(len(ids), int)
    starts = np.r_[True, seg[1:] != seg[:-1]]
    for i in range(len(ids)):
        if starts[i] and np.isfinite(change[i]):
            raise InputError("the first position of a chain has no reading: leave scale_change_mm empty",
                             file=t.path, row=i + 1, field="scale_change_mm")
        if not starts[i] and not np.isfinite(change[i]):
            raise InputError("missing scale change since the previous position", file=t.path, row=i + 1,
                             field="scale_change_mm")
        if np.isfinite(change[i]) and abs(change[i]) > PLAUSIBLE_CHANGE_MM:
            raise InputError(f"scale change {change[i]:g} mm exceeds the scale's range (unit must be mm)",
                             file=t.path, row=i + 1, field="scale_change_mm")
    counts = np.bincount(seg)[1:]
    if np.any(counts < 2):
        k = int(np.flatnonzero(counts < 2)[0])
        row = int(np.flatnonzero(seg == k + 1)[0]) + 1
        raise InputError("a chain of readings needs at least two positions", file=t.path, row=row,
                         field="campaign")
    if len(ids) < min_positions:
        raise InputError(f"{len(ids)} positions; the identification needs at least {min_positions} "
                         f"(K > 5, paper section 4)", file=t.path, field="pose_id")
    r = _plausible_positions(geom, theta, t.path, "theta1_cmd_deg")
    _check_reading_units(geom, r, change, starts, t.path)
    return PlanarMeasurements(ids=ids, theta_cmd=theta, readings=change[~starts], segments=seg, r=r,
                              path=t.path)


def write_measurements(path: str | Path, theta_cmd: np.ndarray, readings: np.ndarray,
                       comments: list[str] = (), ids: list[str] | None = None,
                       segments: np.ndarray | None = None, targets: np.ndarray | None = None) -> None:
    """Write a measurement CSV: ``theta_cmd`` (K, 2) rad, ``readings`` (rows,) mm for each adjacent pair of
    the same chain (``segments``), optional nominal ``targets`` (K, 2) mm as ``x_cmd_mm``, ``y_cmd_mm``."""
    K = len(theta_cmd)
    seg = np.ones(K, int) if segments is None else np.asarray(segments)
    starts = np.r_[True, seg[1:] != seg[:-1]]
    if len(readings) != K - int(starts.sum()):
        raise ValueError("one reading per adjacent pair of a chain")
    ids = ids or [f"P{k + 1}" for k in range(K)]
    header = list(MEAS_COLUMNS) + (["campaign"] if segments is not None else []) \
        + (["x_cmd_mm", "y_cmd_mm"] if targets is not None else [])
    it = iter(readings)
    rows = []
    deg = np.rad2deg(theta_cmd)
    for k in range(K):
        row = [ids[k], f"{deg[k, 0]:.9f}", f"{deg[k, 1]:.9f}", "" if starts[k] else f"{next(it):.6f}"]
        if segments is not None:
            row.append(str(seg[k]))
        if targets is not None:
            row += [f"{targets[k, 0]:.4f}", f"{targets[k, 1]:.4f}"]
        rows.append(row)
    write_csv(path, header, rows, comments=list(comments))


def read_targets(path: str | Path, geom: Geometry) -> tuple[np.ndarray, list[list[str]], list[str]]:
    """Targets CSV: columns ``x_mm``, ``y_mm`` (seed frame, y up, the platform below: y < 0).
    Returns the positions (N, 2) mm and the rows and header as read (to echo them in the setpoints)."""
    t = read_csv(path)
    t.require(["x_mm", "y_mm"])
    r = np.stack([t.numbers("x_mm"), t.numbers("y_mm")], axis=1)
    with np.errstate(over="ignore", invalid="ignore"):      # 1e300 mm: out of reach below, not a warning
        theta = inverse(geom, r)
    bad = ~np.all(np.isfinite(theta), axis=1) | (r[:, 1] >= 0)
    if np.any(bad):
        row = int(np.flatnonzero(bad)[0]) + 1
        raise InputError(f"target ({r[row - 1, 0]:g}, {r[row - 1, 1]:g}) mm is out of the robot's reach "
                         f"(y is negative below the base)", file=t.path, row=row, field="y_mm")
    return r, t.rows, t.header


def write_setpoints(path: str | Path, header: list[str], rows: list[list[str]], theta: np.ndarray,
                    comments: list[str] = ()) -> None:
    """Setpoints CSV: the target rows with ``theta1_deg``, ``theta2_deg`` appended (motor commands)."""
    deg = np.rad2deg(theta)
    out = [list(r) + [f"{deg[i, 0]:.9f}", f"{deg[i, 1]:.9f}"] for i, r in enumerate(rows)]
    write_csv(path, list(header) + ["theta1_deg", "theta2_deg"], out, comments=list(comments))


#: error models of a planar parameters file (docs/planar_measurement_format.md)
PARAM_MODELS = ("simplified", "full", "chain")
#: largest plausible magnitude of a planar error, per unit (beyond: a unit mix-up)
PLAUSIBLE_PARAM = {"deg": 30.0, "mm": 50.0}


def read_params(path: str | Path, *, require_mechanism: bool = True) -> tuple[Errors, dict]:
    """A parameters/errors JSON: ``{"mechanism": "planar_2dof", "params": {key: value}}`` (mm, deg).

    With ``require_mechanism=False`` (error sets for the twin) a flat ``{key: value}`` object is accepted.
    Absent keys are zero. Returns the errors and the whole document.
    """
    p = str(path)
    doc = read_json(path)
    if not isinstance(doc, dict):
        raise InputError("must be a JSON object", file=p)
    if "params" in doc or require_mechanism:
        model = doc.get("model")
        if model is not None and model not in PARAM_MODELS:
            raise InputError(f"unknown model {model!r} (known: {', '.join(PARAM_MODELS)})", file=p, field="model")
        if "stiffness_ratio" in doc:
            raise InputError("planar_2dof has no stiffness ratio (a parameter of ocpm_2dof)", file=p,
                             field="stiffness_ratio")
        mech = doc.get("mechanism")
        if mech != MECHANISM and (require_mechanism or mech is not None):
            raise InputError(f"mechanism is {mech!r}, expected '{MECHANISM}'", file=p, field="mechanism")
        params = doc.get("params")
        prefix = "params."
    else:
        params, prefix = doc, ""
    if not isinstance(params, dict):
        raise InputError("must be an object of parameter values", file=p, field="params")
    for k in params:
        if k not in ERROR_KEYS:
            raise InputError(f"unknown parameter (known: {', '.join(ERROR_KEYS)})", file=p, field=prefix + k)
    values = check_param_values(params, p, interface_unit, PLAUSIBLE_PARAM, prefix)
    return Errors.from_interface(values), doc


def params_document(result: IdentResult, extra: dict | None = None) -> dict:
    """The parameters JSON of an identification (docs/formats.md): values and 1-sigma uncertainties in
    mm and degrees, keys as in :mod:`pmcal.mechanism.planar.geometry`."""
    conv = [(180.0 / math.pi if u == "rad" else 1.0) for u in result.units]
    std = result.std
    doc = {
        "mechanism": MECHANISM,
        "params": {k: float(v * c) for k, v, c in zip(result.names, result.x, conv)},
        "units": {k: interface_unit(k) for k in result.names},
        "method": result.method,
        "model": result.info.get("model"),
        "uncertainty": ({k: float(s * c) for k, s, c in zip(result.names, std, conv)}
                        if std is not None and np.all(np.isfinite(std)) else None),
        "rank": result.info.get("rank"),
        "condition_number": result.info.get("cond"),
        "residual_rms_mm": result.residual_rms,
        "n_readings": result.info.get("n_readings"),
        "success": result.success,
        "message": result.message,
    }
    doc.update(extra or {})
    return doc


