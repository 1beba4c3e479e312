"""File formats of a machine described by a folder (docs/formats.md, "Any machine"): N motors, K tracker
targets, the task coordinates its ``machine.toml`` names.

- measurement CSV: ``pose_id``, ``m1_cmd_deg`` ... ``mN_cmd_deg`` (``_mm`` for a prismatic motor),
  ``t1_x`` ... ``tK_z`` (mm, base frame; a blocked target has its three cells empty), optional ``time_s``
  (s) and ``temp_c`` (degC); a machine measuring a distance (``[tracker] measure = "distance"``) has
  ``reading_mm`` instead of the targets (the scale's reading relative to its reference pose, mm; empty on
  the first pose of a chain) and optionally ``chain`` (a label per pose: a new chain of readings, the
  scale re-zeroed, where it changes);
- plan CSV: ``pose_id`` and the motor columns (the commands to drive, in order);
- targets CSV: the task coordinates (``x_mm, y_mm, z_mm`` ...); setpoints CSV: the same with ``m1_deg`` ...
  ``mN_deg`` (or ``_mm``) appended;
- parameters JSON: ``{"mechanism": NAME, "params": {key: value}, "units": {key: "mm"|"deg"}, ...}``.

Validation happens here, at the edge: one :class:`~pmcal.errors.InputError` naming file, row and field.
The checks that need the machine's kinematics (targets where the nominal machine cannot put them) are the
application's (:mod:`pmcal.apps.chain`).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pmcal.csvio import MAX_POSES, check_blocked, check_context, read_csv, write_columns, write_csv
from pmcal.errors import InputError
from pmcal.fileio import check_param_values, read_json
from pmcal.mechanism.machine_spec import MachineSpec

#: the optional context columns of a measurement CSV
CONTEXT_COLUMNS = ("time_s", "temp_c")
#: the reading column of a machine measuring a distance, and its optional chain label column
READING_COLUMN, CHAIN_COLUMN = "reading_mm", "chain"
#: largest plausible magnitude of a geometric error per unit (beyond it a unit mix-up is likelier)
PLAUSIBLE_PARAM = {"mm": 25.0, "deg": 10.0}
#: per command unit: the factor that turns a value in the likely wrong unit into it (radians, metres), and
#: what to say
UNIT_SLIPS = {"deg": (180.0 / math.pi, "radians: the file must be in degrees"),
               "mm": (1000.0, "metres: the file must be in mm")}


@dataclass
class ChainMeasurements:
    """A measurement file of a machine folder.

    pose_id : list of str; commands : (n, M) deg or mm per motor; targets : (n, K, 3) mm, base frame, NaN for
    a blocked target ((n, 0, 3) for a machine measuring a distance); time_s, temp_c : (n,) or None; path :
    the file (for messages). readings : (n,) mm for a machine measuring a distance, NaN on the first pose
    of each chain (else None); chain : (n,) chain labels (None: one chain); machine : the
    :class:`pmcal.Machine` of the campaign when read through ``pmcal.read_measurements`` (else None).
    """

    pose_id: list[str]
    commands: np.ndarray
    targets: np.ndarray
    time_s: np.ndarray | None = None
    temp_c: np.ndarray | None = None
    path: str = ""
    readings: np.ndarray | None = None
    chain: np.ndarray | None = None
    machine: object = None          # the pmcal.Machine whose campaign this is (set by pmcal.read_measurements)

    def chain_starts(self) -> np.ndarray:
        """(n,) True on the first pose of each chain of readings."""
        c = np.zeros(len(self), int) if self.chain is None else np.asarray(self.chain)
        return np.r_[True, c[1:] != c[:-1]] if len(c) else np.zeros(0, bool)

    def reading_rows(self) -> np.ndarray:
        """The readings (rows,) mm, one per pose but the first of each chain (the rows of
        :func:`pmcal.calib.closed_chain.reading_operator`)."""
        return self.readings[~self.chain_starts()]

    def __len__(self) -> int:
        return len(self.pose_id)


def setpoint_columns(spec: MachineSpec) -> tuple[str, ...]:
    """Setpoint columns: ``m1_deg`` (revolute) / ``m1_mm`` (prismatic) ..."""
    return tuple(f"{m.name}_{m.unit}" for m in spec.motors)


def min_visible_targets(spec: MachineSpec) -> int:
    """Targets a measured row needs: 3 when the platform pose is measured, else 1."""
    return 3 if spec.measure == "pose" else 1


def _check_header(t, spec: MachineSpec, expected: tuple[str, ...], what: str,
                  optional: tuple[str, ...] = CONTEXT_COLUMNS) -> None:
    """Unknown columns, a motor or target the machine does not have (measurement files: also a motor column
    in the wrong unit), missing columns."""
    measurement = "pose_id" in expected
    n_motors, n_targets = len(spec.motors), len(spec.targets)
    for c in t.header:
        if c in expected:
            continue
        motor = re.fullmatch(r"m(\d+)_cmd_(deg|mm)", c) if measurement else None
        if motor and 1 <= int(motor[1]) <= n_motors:
            m = spec.motors[int(motor[1]) - 1]
            raise InputError(f"motor {m.name} of {spec.name} is {m.kind}: its column is {m.name}_cmd_{m.unit}",
                             file=t.path, field=c)
        if motor or (measurement and re.fullmatch(r"t(\d+)_[xyz]", c)):
            raise InputError(f"machine {spec.name} has {n_motors} motors (m1..m{n_motors}) and {n_targets} "
                             f"tracker targets (t1..t{n_targets}): wrong machine (--machine) or file?",
                             file=t.path, field=c)
        raise InputError(f"unknown column in a {what} of {spec.name} (columns: {', '.join(expected)})",
                         file=t.path, field=c)
    t.require(c for c in expected if c not in optional)


def check_commands(commands: np.ndarray, spec: MachineSpec, path: str, columns: tuple[str, ...]) -> None:
    """Every command within its motor's range (machine.toml); a value outside names row and field, and says
    so when the column looks like radians or metres."""
    for j, motor in enumerate(spec.motors):
        lo, hi = motor.range
        col = commands[:, j]
        bad = np.flatnonzero((col < lo) | (col > hi))
        if bad.size:
            factor, slip = UNIT_SLIPS[motor.unit]
            scaled = col * factor
            hint = f" (values look like {slip})" if np.all((scaled >= lo) & (scaled <= hi)) else ""
            i = int(bad[0])
            raise InputError(f"{col[i]:g} {motor.unit} is outside motor {motor.name}'s range {lo:g}..{hi:g} "
                             f"{motor.unit} (machine.toml){hint}", file=path, row=i + 1, field=columns[j])


def read_measurements(path: str | Path, spec: MachineSpec) -> ChainMeasurements:
    """Read and validate a measurement CSV of ``spec``'s machine (module docstring): unknown or missing
    columns, a motor or target the machine does not have, non-numbers and non-finite values, duplicate ids,
    commands outside the motors' ranges (radians? metres?), half-empty targets, rows with fewer measured
    targets than the machine needs, temperatures in the wrong unit.

    Example
    -------
    >>> meas = read_measurements("m.csv", MachineSpec.load("mjcf/delta_3dof"))   # doctest: +SKIP
    >>> meas.commands.shape, meas.targets.shape                                  # doctest: +SKIP
    ((48, 3), (48, 3, 3))
    """
    t = read_csv(path, max_rows=MAX_POSES)
    motors, targets = spec.motor_columns, spec.target_columns
    if spec.measure == "distance":
        return _read_readings(t, spec)
    _check_header(t, spec, ("pose_id",) + motors + targets + CONTEXT_COLUMNS, "measurement file")
    ids = t.unique_ids("pose_id")
    commands = np.stack([t.numbers(c) for c in motors], axis=1)
    check_commands(commands, spec, t.path, motors)
    k = len(spec.targets)
    coords = np.stack([t.numbers(c, allow_empty=True) for c in targets], axis=1).reshape(len(ids), k, 3)
    check_blocked(coords, t.path, min_visible_targets(spec))
    optional = {c: (t.numbers(c, allow_empty=True) if t.has(c) else None) for c in CONTEXT_COLUMNS}
    check_context(t.path, temp_c=optional["temp_c"])
    return ChainMeasurements(pose_id=ids, commands=commands, targets=coords, path=t.path, **optional)


def _read_readings(t, spec: MachineSpec) -> ChainMeasurements:
    """The measurement file of a machine measuring a distance (module docstring): a reading on every pose
    but the first of each chain, none on the first."""
    motors = spec.motor_columns
    _check_header(t, spec, ("pose_id",) + motors + (READING_COLUMN, CHAIN_COLUMN) + CONTEXT_COLUMNS,
                  "measurement file", optional=CONTEXT_COLUMNS + (CHAIN_COLUMN,))
    ids = t.unique_ids("pose_id")
    commands = np.stack([t.numbers(c) for c in motors], axis=1)
    check_commands(commands, spec, t.path, motors)
    readings = t.numbers(READING_COLUMN, allow_empty=True)
    chain = np.array(t.text(CHAIN_COLUMN)) if t.has(CHAIN_COLUMN) else None
    meas = ChainMeasurements(pose_id=ids, commands=commands, targets=np.zeros((len(ids), 0, 3)), path=t.path,
                             readings=readings, chain=chain,
                             **{c: (t.numbers(c, allow_empty=True) if t.has(c) else None) for c in CONTEXT_COLUMNS})
    for i, (first, v) in enumerate(zip(meas.chain_starts(), readings)):
        if chain is not None and chain[i] == "":
            raise InputError("empty chain label", file=t.path, row=i + 1, field=CHAIN_COLUMN)
        if first and np.isfinite(v):
            raise InputError("the first pose of a chain has no reading (the scale is zeroed there): leave "
                             f"{READING_COLUMN} empty", file=t.path, row=i + 1, field=READING_COLUMN)
        if not first and not np.isfinite(v):
            raise InputError("missing reading (relative to the reference pose)", file=t.path, row=i + 1,
                             field=READING_COLUMN)
    check_context(t.path, temp_c=meas.temp_c)
    return meas


def write_measurements(path: str | Path, spec: MachineSpec, meas: ChainMeasurements, comments=()) -> None:
    """Write a measurement CSV (module docstring) atomically; NaN targets (readings) as empty cells."""
    cols = [(c, meas.commands[:, j], "{:.6f}") for j, c in enumerate(spec.motor_columns)]
    if spec.measure == "distance":
        cols.append((READING_COLUMN, meas.readings, "{:.6f}"))
        if meas.chain is not None:
            cols.append((CHAIN_COLUMN, np.asarray(meas.chain, float), "{:.0f}"))
    cols += [(c, meas.targets[:, i // 3, i % 3], "{:.5f}") for i, c in enumerate(spec.target_columns)
             if spec.measure != "distance"]
    for name, values, fmt in (("time_s", meas.time_s, "{:.2f}"), ("temp_c", meas.temp_c, "{:.3f}")):
        if values is not None:
            cols.append((name, np.asarray(values, float), fmt))
    write_columns(path, "pose_id", meas.pose_id, cols, comments)


def write_plan(path: str | Path, spec: MachineSpec, commands: np.ndarray, comments=()) -> None:
    """A campaign plan CSV: ``pose_id`` (``P1`` ...) and the motor columns of the measurement file, in the
    order to drive (``pmcal --machine DIR twin plan``)."""
    cols = [(c, np.asarray(commands, float)[:, j], "{:.6f}") for j, c in enumerate(spec.motor_columns)]
    write_columns(path, "pose_id", [f"P{i + 1}" for i in range(len(commands))], cols, comments)


def read_plan(path: str | Path, spec: MachineSpec) -> tuple[list[str], np.ndarray]:
    """A campaign plan CSV (:func:`write_plan`): its pose ids and commands (n, M), each within its motor's
    range."""
    t = read_csv(path, max_rows=MAX_POSES)
    motors = spec.motor_columns
    _check_header(t, spec, ("pose_id",) + motors, "plan")
    ids = t.unique_ids("pose_id")
    commands = np.stack([t.numbers(c) for c in motors], axis=1)
    check_commands(commands, spec, t.path, motors)
    return ids, commands


def read_targets(path: str | Path, spec: MachineSpec) -> np.ndarray:
    """Task coordinates (n, C) from a targets CSV: exactly the machine's task columns, each row inside the
    workspace box of machine.toml (a value outside names row and field)."""
    t = read_csv(path, max_rows=MAX_POSES * 50)
    columns = spec.task.coordinates
    _check_header(t, spec, columns, "targets file")
    task = np.stack([t.numbers(c) for c in columns], axis=1)
    for j, c in enumerate(columns):
        lo, hi = spec.workspace[c]
        bad = np.flatnonzero((task[:, j] < lo) | (task[:, j] > hi))
        if bad.size:
            i = int(bad[0])
            unit = c.rsplit("_", 1)[-1]
            raise InputError(f"{task[i, j]:g} {unit} is outside the workspace {lo:g}..{hi:g} {unit} of "
                             f"machine.toml", file=t.path, row=i + 1, field=c)
    return task


def write_targets(path: str | Path, spec: MachineSpec, task: np.ndarray, comments=()) -> None:
    """A targets CSV: the machine's task columns, mm and deg."""
    write_csv(path, spec.task.coordinates, np.asarray(task, float), comments)


def write_setpoints(path: str | Path, spec: MachineSpec, task: np.ndarray, commands: np.ndarray,
                    comments=()) -> None:
    """Setpoints CSV: the targets' task columns with the motor commands that reach them appended
    (``m1_deg`` ... or ``_mm``)."""
    rows = np.concatenate([np.asarray(task, float), np.asarray(commands, float)], axis=1)
    write_csv(path, spec.task.coordinates + setpoint_columns(spec), rows, comments)


def read_params(path: str | Path, spec: MachineSpec, units: dict[str, str]) -> tuple[dict[str, float], dict]:
    """A parameters JSON of ``spec``'s machine: ``mechanism`` its name, ``params`` keys among ``units`` (error
    key -> "mm" | "deg", the twin's), finite values of plausible size. Returns (params, whole document);
    a key that is absent is nominal (zero)."""
    p = str(path)
    doc = read_json(path)
    if not isinstance(doc, dict) or not isinstance(doc.get("params"), dict):
        raise InputError("expected an object with a 'params' object", file=p, field="params")
    mech = doc.get("mechanism")
    if mech != spec.name:
        raise InputError(f"parameters are for mechanism {mech!r}, not {spec.name!r} (wrong --machine?)", file=p,
                         field="mechanism")
    for key in doc["params"]:
        if key not in units:
            raise InputError(f"not an error of {spec.name} (keys look like {', '.join(list(units)[:3])}, ...)",
                             file=p, field=f"params.{key}")
    return check_param_values(doc["params"], p, units.__getitem__, PLAUSIBLE_PARAM), doc
