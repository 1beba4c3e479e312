"""Tracker exports and controller logs in, the measurement CSV out (``pmcal import``, docs/formats.md).

A real campaign leaves two files: the metrology package's export of named points (Spatial Analyzer's
ASCII point export, or any CSV of named points with a column map) and the controller's log of the motor
commands per pose. :func:`pmcal.ocpm.io.join` matches each point to a pose of the log (by the pose number in its name,
or by the nearest time stamp) and to a nest on the platform (by its target name) and returns the
:class:`pmcal.mechanism.ocpm.data.Measurements` of the documented measurement file, with a report of every
point it could not place; :func:`join_machine` the same for a machine folder (its N motor columns and K
nests, :class:`pmcal.io_chain.ChainMeasurements`), both on :func:`place_points`.

Units out: mm. Spatial Analyzer's export is in the working frame of the SA job; :func:`pmcal.ocpm.io.in_base_frame`
tells whether that frame is the machine's base frame (otherwise identify needs ``--frame tracker``).
"""

from __future__ import annotations

import contextlib
import math
import re
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Iterator

import numpy as np

from pmcal.csvio import MAX_CSV_BYTES, parse_number, read_csv
from pmcal.errors import InputError
from pmcal.csvio import MAX_POSES, check_context, check_time_order
from pmcal.io_chain import ChainMeasurements

#: millimetres per unit of length a tracker export may use
UNITS_MM = {"mm": 1.0, "in": 25.4}
#: words in a ``//`` header line that name the export's length unit
UNIT_WORDS = {"in": ("inch", "inches"), "mm": ("millimeter", "millimeters", "millimetre", "millimetres")}
#: default name pattern: the last name field is the target (nest), the one before it the group (pose);
#: a leading collection name is ignored
DEFAULT_NAMES = r"(?:(?:(?P<collection>\S+) )?(?P<pose>\S+) )?(?P<target>\S+)"
#: working-frame names taken as the machine's base frame (case-insensitive; SA writes COLLECTION::FRAME)
BASE_FRAME_NAMES = ("base", "base frame", "machine base", "o-xyz")
#: Largest distance between the measured platform centre and where the commands put the nominal
#: machine's, and largest pointing disagreement, for points still read as base-frame coordinates (mm, deg).
BASE_FRAME_LIMITS = (20.0, 5.0)
#: time-stamp layouts tried after ISO 8601 (Spatial Analyzer writes the Windows locale's date and time)
TIME_FORMATS = ("%m/%d/%Y %I:%M:%S %p", "%m/%d/%Y %H:%M:%S", "%d.%m.%Y %H:%M:%S", "%m/%d/%Y %I:%M:%S.%f %p",
                "%m/%d/%Y %H:%M:%S.%f", "%d.%m.%Y %H:%M:%S.%f")
#: CSV column-map keys: name (or pose and target), x, y, z required; time optional
COLUMN_KEYS = ("name", "pose", "target", "x", "y", "z", "time")


@dataclass
class TrackerPoint:
    """One exported point: its name fields, coordinates (mm, the export's frame), time stamp (s, or NaN)
    and where it is in the file (``FILE:LINE`` or ``FILE row N``, for messages)."""

    name: str
    xyz: np.ndarray
    time_s: float
    where: str
    pose: str | None = None         # pose label, when a column gives it (plain CSV)
    target: str | None = None       # target label, when a column gives it


@dataclass
class TrackerExport:
    """The points of a tracker export, in mm, with what its header said.

    ``units`` the unit the file was written in (``mm`` or ``in``; the points are converted to mm);
    ``frame`` the working-frame name of the header, or None; ``version`` the SA version line, or None."""

    path: str
    kind: str
    points: list[TrackerPoint]
    units: str
    frame: str | None = None
    version: str | None = None
    warnings: list[str] = field(default_factory=list)


def _is_number(tok: str) -> bool:
    return _is_float(tok) and math.isfinite(float(tok))


def _is_float(tok: str) -> bool:
    """A number, finite or not: where a coordinate is ``nan`` or ``inf`` it is refused by name, not read as a name
    (:func:`pmcal.csvio.parse_number`: ``1_000`` is none)."""
    try:
        parse_number(tok)
        return True
    except ValueError:
        return False


def parse_time(text: str, where: str, field_name: str = "time") -> float:
    """A time stamp as seconds: a number (s, any clock) or a date and time (ISO 8601 or the layouts of
    :data:`TIME_FORMATS`, read as UTC) as seconds since 1970-01-01. InputError naming ``where``."""
    text = text.strip()
    if _is_number(text):
        return float(text)
    stamp = None
    try:
        stamp = datetime.fromisoformat(text)
    except ValueError:
        for fmt in TIME_FORMATS:
            try:
                stamp = datetime.strptime(text, fmt)
                break
            except ValueError:
                continue
    if stamp is None:
        raise InputError(f"'{text}' is not a time stamp (seconds, or a date and time such as "
                         "2026-11-25 10:15:32.5 or 11/25/2026 10:15:32 AM)", file=where, field=field_name)
    if stamp.tzinfo is None:
        stamp = stamp.replace(tzinfo=timezone.utc)
    return stamp.timestamp()


def _header_units(line: str) -> str | None:
    words = re.findall(r"[a-z]+", line.lower())
    if "unit" not in " ".join(words) and not any(w in words for ws in UNIT_WORDS.values() for w in ws):
        return None
    for unit, names in UNIT_WORDS.items():
        if any(w in words for w in names):
            return unit
    return None


def check_units(units: str | None) -> str | None:
    if units is not None and units not in UNITS_MM:
        raise InputError(f"unknown unit '{units}' (known: {', '.join(UNITS_MM)})", field="--units")
    return units


def read_sa_ascii(path: str | Path, units: str | None = None) -> TrackerExport:
    """Read Spatial Analyzer's ASCII point export (Cartesian coordinates).

    Layout, per the export options of SA's manual: optional ``//`` comment lines first (SA version,
    working frame ``// Frame: NAME``, axis comments, a unit line); then one point per line: its name
    as ``Collection Group Target``, ``Group Target`` or ``Target`` (the same number of name fields on
    every line; names without spaces), the coordinates ``x y z``, and optionally tolerance and
    uncertainty numbers and a time stamp (date and time, or seconds), separated by spaces or commas.

    Parameters
    ----------
    path : str or Path
        The export.
    units : {"mm", "in"}, optional
        Unit of the coordinates; default the header's unit line, else mm. Points come back in mm.

    Returns
    -------
    TrackerExport

    Raises
    ------
    pmcal.errors.InputError
        Naming ``FILE:LINE`` and the field (``name``, ``x``, ``y``, ``z``, ``time``).

    Examples
    --------
    >>> exp = read_sa_ascii("campaign.txt", units="in")      # doctest: +SKIP
    >>> exp.points[0].name, exp.points[0].xyz                # doctest: +SKIP
    ('MACHINE P001 T1', array([ 60.01,   0.02, 480.  ]))
    """
    p = str(path)
    units = check_units(units)
    raw = _read_text(path)
    header_units, frame, version, data = None, None, None, []
    for n, line in enumerate(raw.splitlines(), start=1):
        s = line.strip()
        if not s:
            continue
        if s.startswith("//"):
            text = s.lstrip("/").strip()
            low = text.lower()
            if "frame" in low and ":" in text and frame is None:
                frame = text.split(":", 1)[1].strip()
            elif ("spatialanalyzer" in low.replace(" ", "") or low.startswith("sa ")) and version is None:
                version = text
            named = _header_units(text)
            if named is None and units is None and re.match(r"units?\s*:", low):     # Meters, Feet: not mm
                raise InputError(f"the unit line says '{text.split(':', 1)[1].strip()}': pmcal reads Millimeters or "
                                 "Inches (export in one of them, or give --units)", file=f"{p}:{n}", field="units")
            header_units = header_units or named
            continue
        toks = [t for t in re.split(r"[,\s]+", s) if t]
        first = next((i for i in range(1, len(toks) - 2) if all(_is_float(t) for t in toks[i:i + 3])), None)
        if first is None:
            raise InputError("expected a point: NAME x y z (name fields, then three numbers)", file=f"{p}:{n}",
                             field="x")
        data.append((n, toks, first))
    if not data:
        raise InputError("no points (only comment lines)", file=p)
    warnings = []
    if units and header_units and units != header_units:
        warnings.append(f"{p}: the header says {header_units}, --units {units} wins")
    unit = units or header_units or "mm"
    scale = UNITS_MM[unit]
    n_name = max(f for _, _, f in data)          # a numeric target name shortens a line's guess, never lengthens
    points = []
    for n, toks, _ in data:
        where = f"{p}:{n}"
        if len(toks) < n_name + 3:
            raise InputError(f"{len(toks)} fields where the file's points have {n_name} name fields and x y z",
                             file=where, field="z")
        for k, axis in enumerate("xyz"):
            if not _is_number(toks[n_name + k]):
                what = "a finite number" if _is_float(toks[n_name + k]) else "a number"
                raise InputError(f"'{toks[n_name + k]}' is not {what}", file=where, field=axis)
        tail = toks[n_name + 3:]
        t_start = next((i for i, t in enumerate(tail) if not _is_number(t)), None)
        stamp = math.nan
        if t_start is not None:
            stamp = parse_time(" ".join(tail[t_start:]), where)
        elif len(tail) >= 3 and float(tail[-1]) > 1e6:     # seconds since an epoch after tolerance/uncertainty
            stamp = float(tail[-1])
        xyz = np.array([float(v) for v in toks[n_name:n_name + 3]]) * scale
        points.append(TrackerPoint(name=" ".join(toks[:n_name]), xyz=xyz, time_s=stamp, where=where))
    return TrackerExport(path=p, kind="Spatial Analyzer ASCII", points=points, units=unit, frame=frame,
                         version=version, warnings=warnings)


def _read_text(path: str | Path) -> str:
    p = str(path)
    try:
        if Path(path).is_file() and Path(path).stat().st_size > MAX_CSV_BYTES:
            raise InputError(f"larger than the {MAX_CSV_BYTES // 2**20} MiB pmcal reads", file=p)
        return Path(path).read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise InputError("file not found", file=p) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read file ({exc.__class__.__name__}: {exc})", file=p) from None


def parse_columns(text: str) -> dict[str, str]:
    """``--columns name=Point,x=X,y=Y,z=Z[,time=T]`` (or ``pose=..,target=..`` instead of ``name``)."""
    out = {}
    for part in (q.strip() for q in text.split(",") if q.strip()):
        key, sep, col = part.partition("=")
        if not sep or key.strip() not in COLUMN_KEYS or not col.strip():
            raise InputError(f"'{part}' is not KEY=COLUMN with KEY one of {', '.join(COLUMN_KEYS)}",
                             field="--columns")
        if key.strip() in out:
            raise InputError(f"'{key.strip()}' is given twice ({out[key.strip()]}, {col.strip()})", field="--columns")
        out[key.strip()] = col.strip()
    if "name" in out and ("pose" in out or "target" in out):
        raise InputError("give name=COL, or pose=COL,target=COL instead of it, not both", field="--columns")
    missing = [k for k in ("x", "y", "z") if k not in out]
    if not ("name" in out or ("pose" in out and "target" in out)):
        missing.insert(0, "name (or pose and target)")
    if missing:
        raise InputError(f"the column map lacks {', '.join(missing)}", field="--columns")
    return out


def read_point_csv(path: str | Path, columns: dict[str, str], units: str | None = None) -> TrackerExport:
    """Read a plain CSV of named points (a header row; ``#`` comments) with a column map
    (:func:`parse_columns`): name or pose + target, x, y, z, optional time (seconds or date and time).
    ``units`` ``mm`` (default) or ``in``; points come back in mm."""
    unit = check_units(units) or "mm"
    t = read_csv(path)
    t.require(list(columns.values()))
    xyz = np.stack([t.numbers(columns[a]) for a in "xyz"], axis=1) * UNITS_MM[unit]
    text = {k: t.text(columns[k]) for k in ("name", "pose", "target", "time") if k in columns}
    points = []
    for i in range(len(xyz)):
        where = f"{t.path} row {i + 1}"
        stamp = parse_time(text["time"][i], where, columns["time"]) if text.get("time") and text["time"][i] \
            else math.nan
        name = text["name"][i] if "name" in text else f"{text['pose'][i]} {text['target'][i]}"
        points.append(TrackerPoint(name=name, xyz=xyz[i], time_s=stamp, where=where,
                                   pose=text["pose"][i] if "pose" in text else None,
                                   target=text["target"][i] if "target" in text else None))
    frame = next((c.split(":", 1)[1].strip() for c in t.comments if c.lower().startswith("frame")), None)
    return TrackerExport(path=t.path, kind="point CSV", points=points, units=unit, frame=frame)


@dataclass
class ControllerLog:
    """The controller's log: one row per commanded pose, in the order driven.

    pose_id : labels as written; commands : (N, M) commanded motor positions in the columns' units (deg,
    or mm for a prismatic motor); time_s, temp_c : (N,) or None."""

    path: str
    pose_id: list[str]
    commands: np.ndarray
    time_s: np.ndarray | None
    temp_c: np.ndarray | None


#: motor columns of the seeded ocpm_2dof's log
OCPM_MOTOR_COLUMNS = ("m1_cmd_deg", "m2_cmd_deg")


def read_controller_log(path: str | Path, motor_columns: tuple[str, ...] = OCPM_MOTOR_COLUMNS) -> ControllerLog:
    """Read the controller log CSV: ``pose_id``, the motor columns (``m1_cmd_deg``, ``m2_cmd_deg`` for
    ocpm_2dof; a machine folder's ``m1_cmd_deg`` .. ``mN_cmd_mm``), optional ``time_s`` (s; or ``time``, a
    date and time) and ``temp_c`` (degC). Ids unique; InputError naming row and field."""
    t = read_csv(path, max_rows=MAX_POSES)
    t.require(["pose_id", *motor_columns])
    ids = t.unique_ids("pose_id")
    m = np.stack([t.numbers(c) for c in motor_columns], axis=1)
    time_s = None
    if t.has("time_s"):
        time_s = t.numbers("time_s")
        check_time_order(time_s, t.path)
    elif t.has("time"):
        time_s = np.array([parse_time(v, f"{t.path} row {i + 1}", "time") for i, v in enumerate(t.text("time"))])
        check_time_order(time_s, t.path, "time")
    temp = t.numbers("temp_c") if t.has("temp_c") else None
    check_context(t.path, temp_c=temp)
    return ControllerLog(path=t.path, pose_id=ids, commands=m, time_s=time_s, temp_c=temp)


@dataclass
class ImportResult:
    """What :func:`pmcal.ocpm.io.join` made: the measurements, how it joined, and every point it could not place.

    ``meas`` rows are the log's poses in log order (poses with fewer than two points left out, listed in
    ``left_out``); ``frame`` is ``base`` or ``tracker`` (:func:`pmcal.ocpm.io.in_base_frame`, ``frame_reason`` why not
    the base frame); ``warnings`` one line each
    (unmatched, re-shot, ambiguous points by name and line); ``comments`` the header lines of the file."""

    meas: object                    # ocpm_2dof's Measurements (pmcal.ocpm.io.join) or ChainMeasurements
    frame: str
    frame_reason: str
    join: str
    warnings: list[str]
    left_out: list[str]
    blocked: list[str]
    comments: list[str]


def pose_number(label: str) -> int | None:
    """The last run of digits in a pose label as a number (``P007`` -> 7, ``pose-12`` -> 12), else None."""
    found = re.findall(r"\d+", label)
    return int(found[-1]) if found else None


def compile_names(pattern: str | None) -> re.Pattern:
    """The ``--names`` regular expression (named groups ``pose`` and/or ``target``), matched against the
    point's name fields joined by single spaces."""
    text = DEFAULT_NAMES if pattern is None else pattern
    try:
        rx = re.compile(text)
    except re.error as exc:
        raise InputError(f"not a regular expression ({exc})", field="--names") from None
    if "target" not in rx.groupindex:
        raise InputError("the pattern needs a named group (?P<target>...) for the nest", field="--names")
    return rx


def join_machine(export: TrackerExport, log: ControllerLog, spec, distance_from_nominal,
                 names: str | None = None, time_tolerance_s: float | None = None) -> ImportResult:
    """:func:`pmcal.ocpm.io.join` for a machine folder (``spec``: its :class:`~pmcal.mechanism.machine_spec.MachineSpec`):
    ``log`` read with the machine's motor columns, a point's target named ``T<k>``, ``<k>`` or the nest's
    site name in machine.toml (``[tracker] targets``), poses kept with at least the targets the machine
    needs (3 when the platform pose is measured, else 1). The frame check: the export's working frame
    name, and the measured nests within :data:`BASE_FRAME_LIMITS` (median) of where the nominal machine
    puts them at the logged commands (``distance_from_nominal(commands, targets) -> (n, K) mm``)."""
    placed = place_points(export, log, list(spec.targets), names, time_tolerance_s,
                          min_points=3 if spec.measure == "pose" else 1)
    idx = placed.keep
    meas = ChainMeasurements(pose_id=[log.pose_id[i] for i in idx], commands=log.commands[idx],
                             targets=placed.coords[idx], temp_c=None if log.temp_c is None else log.temp_c[idx],
                             time_s=None if log.time_s is None else log.time_s[idx], path=log.path)
    base, reason = named_base_frame(export.frame)
    if base and len(meas):
        d = distance_from_nominal(meas.commands, meas.targets)
        med = float(np.nanmedian(np.where(np.isfinite(d), d, np.nan))) if np.isfinite(d).any() else math.inf
        if not med <= BASE_FRAME_LIMITS[0]:
            base, reason = False, (f"the nests are {med:.3g} mm (median) from where the commands put them in the "
                                   "base frame")
    return placed.result(export, log, meas, base, reason,
                         "transform the points into the machine's base frame before identifying")


#: how many points a warning about several points left out for one reason names (the first ones, in file order)
LEFT_OUT_NAMED = 3


class LeftOutPoints:
    """The exported points :func:`place_points` leaves out, by reason: one warning line per reason, however
    many points it holds (an export of thousands of stray points gives a few lines, not thousands)."""

    def __init__(self) -> None:
        self.by_reason: dict[str, list[tuple[TrackerPoint, str]]] = {}

    def add(self, pt: TrackerPoint, why: str, reason: str) -> None:
        """Leave out ``pt``: ``why`` worded for this point, ``reason`` for several (its group)."""
        self.by_reason.setdefault(reason, []).append((pt, why))

    def lines(self, path: str) -> list[str]:
        """One line per reason: the point's own line for a single point, else the count and the first
        :data:`LEFT_OUT_NAMED` points by name and ``FILE:LINE``."""
        out = []
        for reason, items in self.by_reason.items():
            if len(items) == 1:
                pt, why = items[0]
                out.append(f"{pt.where}: point '{pt.name}': {why}: left out")
                continue
            named = ", ".join(f"'{pt.name}' ({pt.where})" for pt, _ in items[:LEFT_OUT_NAMED])
            more = f" and {len(items) - LEFT_OUT_NAMED} more" if len(items) > LEFT_OUT_NAMED else ""
            out.append(f"{path}: {len(items)} points {reason}: left out ({named}{more})")
        return out


@dataclass
class PlacedPoints:
    """Tracker points placed on the log's poses and the machine's nests (:func:`place_points`).

    coords : (N, K, 3) mm, one row per log row, NaN where no point; keep : log rows with enough points;
    slots : (row, nest) -> the point kept; warnings, left_out, blocked : lines for the user; how : the
    join's wording."""

    coords: np.ndarray
    keep: np.ndarray
    slots: dict
    warnings: list[str]
    left_out: list[str]
    blocked: list[str]
    how: str

    def result(self, export: TrackerExport, log: ControllerLog, meas, base: bool, reason: str,
               advice: str) -> ImportResult:
        """The :class:`ImportResult` with the header comments of the measurement file."""
        frame = "base" if base else "tracker"
        comments = [f"pmcal import: tracker {export.path} ({export.kind}"
                    + (f", {export.version}" if export.version else "")
                    + (f", working frame '{export.frame}'" if export.frame else "") + f"), log {log.path}",
                    f"units: mm (export in {export.units}" + (", converted x 25.4)" if export.units == "in" else ")"),
                    f"frame: {frame}" + ("" if base else f" ({reason}): {advice}"),
                    f"joined {self.how}: {len(self.slots)} points, {len(self.keep)} poses, {len(self.blocked)} "
                    "blocked targets" + (f" ({', '.join(self.blocked)})" if self.blocked else "")]
        return ImportResult(meas=meas, frame=frame, frame_reason=reason, join=self.how,
                            warnings=export.warnings + self.warnings, left_out=self.left_out, blocked=self.blocked,
                            comments=comments)


def place_points(export: TrackerExport, log: ControllerLog, nests: list[str], names: str | None,
                 time_tolerance_s: float | None, min_points: int) -> PlacedPoints:
    """Place each exported point on a pose of the log and a nest (``nests``: the nests' names in order;
    a target label ``T<k>``, ``<k>`` or a nest's name, case-insensitive), as :func:`pmcal.ocpm.io.join` describes; poses
    with fewer than ``min_points`` points are left out."""
    rx = compile_names(names)
    n_nests = len(nests)
    by_name = {n.lower(): k for k, n in enumerate(nests)}
    by_number: dict[int, int] = {}
    for i, pid in enumerate(log.pose_id):
        k = pose_number(pid)
        if k is not None:
            if k in by_number:
                raise InputError(f"pose ids '{log.pose_id[by_number[k]]}' and '{pid}' have the same number {k}: "
                                 "points cannot be told apart by pose", file=log.path, row=i + 1, field="pose_id")
            by_number[k] = i
    warnings, slots, left = [], {}, LeftOutPoints()
    times = log.time_s
    nest_names = f"T1..T{n_nests}" + (f" or {', '.join(nests)}" if nests[0] != "T1" else "")
    for pt in export.points:
        pose_label, target_label = pt.pose, pt.target
        if target_label is None:
            mt = rx.fullmatch(pt.name)
            if mt is None or not mt.groupdict().get("target"):
                left.add(pt, "does not fit the name pattern", "do not fit the name pattern")
                continue
            target_label, pose_label = mt.group("target"), mt.groupdict().get("pose")
        number = re.fullmatch(r"[Tt]?(\d+)", target_label)
        nest = by_name.get(target_label.lower(), int(number.group(1)) - 1 if number else -1)
        if not 0 <= nest < n_nests:
            left.add(pt, f"'{target_label}' is not a nest of the machine ({nest_names})",
                     f"name no nest of the machine ({nest_names})")
            continue
        row = None
        if pose_label is not None and pose_number(pose_label) is not None:
            row = by_number.get(pose_number(pose_label))
            if row is None:
                left.add(pt, f"no pose {pose_number(pose_label)} in the log", "name a pose that is not in the log")
                continue
        elif math.isfinite(pt.time_s) and times is not None and time_tolerance_s is not None:
            near = np.flatnonzero(np.abs(times - pt.time_s) <= time_tolerance_s)
            if len(near) != 1:
                what = "no log row" if len(near) == 0 else \
                    "log rows " + ", ".join(log.pose_id[i] for i in near) + " (ambiguous)"
                left.add(pt, f"{what} within {time_tolerance_s:g} s",
                         f"have {'no log row' if len(near) == 0 else 'two or more log rows (ambiguous)'} within "
                         f"{time_tolerance_s:g} s")
                continue
            row = int(near[0])
        else:
            need = "--time-tolerance S and time stamps on both sides" if pose_label is None else "a pose number"
            left.add(pt, f"has no pose in its name ({need} to join it)",
                     f"have no pose in their name ({need} to join them)")
            continue
        key = (row, nest)
        if key in slots:
            warnings.append(f"{pt.where}: point '{pt.name}' measured again (first at {slots[key].where}): "
                            "the last one is kept")
        slots[key] = pt
    warnings = left.lines(export.path) + warnings
    if not slots:
        raise InputError(f"no point of the export matches a pose of the log {log.path} (names, --names pattern, pose "
                         "numbers, time stamps?)" + (f"; first: {warnings[0]}" if warnings else ""), file=export.path)
    N = len(log.pose_id)
    coords = np.full((N, n_nests, 3), np.nan)
    for (row, n), pt in slots.items():
        coords[row, n] = pt.xyz
    n_vis = np.isfinite(coords).all(axis=2).sum(axis=1)
    keep = n_vis >= min_points
    left_out = [f"{log.pose_id[i]} (log row {i + 1}): {n_vis[i]} point(s)" for i in np.flatnonzero(~keep)]
    few = "fewer than two" if min_points == 2 else f"fewer than {min_points}"
    warnings += [f"pose {s}, {few}: left out" for s in left_out]
    blocked = [f"pose {log.pose_id[i]} T{n + 1}" for i in np.flatnonzero(keep) for n in range(n_nests)
               if not np.isfinite(coords[i, n]).all()]
    by_time = any(pt.pose is None and rx.fullmatch(pt.name) is not None and
                  rx.fullmatch(pt.name).groupdict().get("pose") is None for pt in slots.values())
    how = f"by nearest time within {time_tolerance_s:g} s" if by_time else "by pose number"
    return PlacedPoints(coords=coords, keep=np.flatnonzero(keep), slots=slots, warnings=warnings,
                        left_out=left_out, blocked=blocked, how=how)


@contextlib.contextmanager
def export_pose_errors(meas, tracker: str, units: str | None) -> Iterator[None]:
    """Inside, an :class:`InputError` naming a row of the imported measurements ``meas`` (a check of the join's
    result, such as :func:`pmcal.csvio.check_nest_distances`) is about the tracker export: re-raised naming
    the export ``tracker`` and the row's pose, with the unit to check (``units``: the ``--units`` given)."""
    try:
        yield
    except InputError as exc:
        pose = meas.pose_id[exc.row - 1] if exc.row else None
        unit = f"--units {units}" if units else "the unit its header names (else --units)"
        raise InputError(f"pose {pose}: {exc.message}; check the export's unit ({unit})", file=tracker) from None


def named_base_frame(frame_name: str | None) -> tuple[bool, str]:
    """Whether the export's working-frame name (if any) is the machine's base frame, and why not."""
    if frame_name:
        short = frame_name.split("::")[-1].strip().lower()
        if short not in BASE_FRAME_NAMES:
            return False, f"working frame '{frame_name}' is not the machine's base frame"
    return True, ""
