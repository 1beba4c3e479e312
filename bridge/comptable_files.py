"""The compensation table's files: JSON and CSV of format 4, and the reading of formats 1 to 3.

Specification: ``docs/compensation_table.md`` ("Files"). Both files carry the table's CRC-32 (the PLC's:
header image and data) and SHA-256; reading compares them with the data, so an edited or damaged file
is refused. Floats are written with ``repr`` and read back bit for bit. Writing is atomic
(:func:`pmcal.fileio.atomic_write`). Formats 1 to 3 (two axes phi/theta, two motors m1/m2 with shared
limits) are read and become format-4 tables; their CRC is checked with the layout they were written with.
"""

from __future__ import annotations

import binascii
import csv
import hashlib
import json
import struct
from pathlib import Path

import numpy as np

from pmcal.bridge.comptable import (CONTROLLER, FORMAT, FORMAT_VERSION, NMOTOR_MAX, PHI, READ_VERSIONS, THETA, Axis,
                                    CompTable, ControllerReference, Motor, crc32)
from pmcal.bridge.nominal import NominalReference
from pmcal.csvio import parse_number
from pmcal.errors import InputError
from pmcal.fileio import atomic_write, read_json as read_json_document

#: ST_CompTableHeader of format 3 (104 bytes), for the CRC of format-3 files
_HEADER_V3 = struct.Struct("<7dI4H2I28s")
#: What a table CSV starts with: a file beside a table's JSON is replaced only if it is one
SIDE_FILE_START = f"# {FORMAT} "
_AXIS_KEYS = ("name", "unit", "min", "max", "n")
_MOTOR_KEYS = ("name", "unit", "min", "max", "max_step")


def header_dict(table: CompTable) -> dict:
    """Header fields as written to JSON (also the CSV comment block)."""
    return {
        "format": FORMAT, "format_version": FORMAT_VERSION, "machine": table.machine,
        "table_version": int(table.version),
        "axes": [{"name": a.name, "unit": a.unit, "min": a.min, "max": a.max, "n": a.n} for a in table.axes],
        "motors": [{"name": m.name, "unit": m.unit, "min": m.min, "max": m.max, "max_step": m.max_step}
                   for m in table.motors],
        "reference": {"kind": "none"} if table.reference is None else table.reference.as_dict(),
        "crc32": f"0x{table.crc32():08X}", "sha256": table.sha256(),
    }


def write_json(table: CompTable, path: str | Path) -> None:
    """Write the JSON file atomically (header, nested ``values[i0][i1]..[k]``, checksums)."""
    doc = header_dict(table)
    idx = "".join(f"[i_{a.name}]" for a in table.axes)
    what = ("absolute commands" if table.reference is None else
            "corrections added to the motion controller's own nominal IK (motor min/max/max_step bound the "
            "corrections)" if table.controller_reference else "corrections added to the nominal IK of 'reference'")
    doc["layout"] = (f"values{idx} = [{', '.join(c for c in table.columns()[table.n_axes:])}]: {what}; "
                     "node = min + index*(max-min)/(n-1)")
    doc["values"] = table.values.tolist()
    try:
        text = json.dumps(doc, indent=1, allow_nan=False)
    except ValueError:
        raise InputError("table holds NaN or infinite values; not written", file=str(path), field="values") from None
    with atomic_write(path) as fh:
        fh.write(text + "\n")


def write_csv(table: CompTable, path: str | Path) -> None:
    """Write the CSV atomically: ``#`` header lines, then one row per node in memory order."""
    h = header_dict(table)
    with atomic_write(path) as fh:
        fh.write(f"# {FORMAT} format_version={FORMAT_VERSION}\n")
        fh.write(f"# machine={table.machine}\n# table_version={table.version}\n")
        for a in h["axes"]:
            fh.write("# axis " + " ".join(f"{k}={_num(v) if k in ('min', 'max') else v}" for k, v in a.items()) + "\n")
        for m in h["motors"]:
            fh.write("# motor " + " ".join(f"{k}={v if k in ('name', 'unit') else _num(v)}" for k, v in m.items())
                     + "\n")
        fh.write("# reference " + " ".join(f"{k}={v if k == 'kind' else _num(v)}"
                                           for k, v in h["reference"].items()) + "\n")
        fh.write(f"# crc32={h['crc32']} sha256={h['sha256']}\n")
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(table.columns())
        x = table.nodes().reshape(-1, table.n_axes)
        v = table.values.reshape(-1, table.n_motors)
        for row_x, row_v in zip(x, v):
            w.writerow([_num(c) for c in row_x] + [_num(c) for c in row_v])


def read_json(path: str | Path) -> CompTable:
    """Read and check a JSON table (structure, grid shape, checksums); values not validated."""
    src = str(path)
    doc = read_json_document(path)
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise InputError(f"not a compensation table (expected \"format\": \"{FORMAT}\")", file=src, field="format")
    fv = _check_format_version(doc.get("format_version"), src)
    reference = None if fv == 1 else _reference(_section(doc, "reference", src), src)
    if fv >= 4:
        axes = [_axis({k: _get(a, k, src, "axes") for k in _AXIS_KEYS}, src) for a in _list(doc, "axes", src)]
        motors = [_motor({k: _get(m, k, src, "motors") for k in _MOTOR_KEYS}, src) for m in _list(doc, "motors", src)]
    else:
        axes, motors = _legacy(_section(doc, "grid", src), _section(doc, "limits", src), src, _float, _int)
    shape = tuple(a.n for a in axes) + (len(motors),)
    try:
        values = np.asarray(doc.get("values"), dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"values must be numbers nested {list(shape)}", file=src, field="values") from None
    if values.shape != shape:
        raise InputError(f"values have shape {values.shape}, header says {shape}", file=src, field="values")
    table = CompTable(machine=_str(doc, "machine", src), version=_int(doc, "table_version", src), axes=axes,
                      motors=motors, values=values, reference=reference, source=src)
    _check_sums(table, doc, src, fv)
    return table


def read_csv(path: str | Path) -> CompTable:
    """Read and check a CSV table (header comments, node coordinates, checksums)."""
    src = str(path)
    try:
        lines = Path(path).read_text(encoding="utf-8-sig").splitlines()
    except FileNotFoundError:
        raise InputError("file not found", file=src) from None
    except UnicodeDecodeError:
        raise InputError("not a UTF-8 text file", file=src) from None
    meta: dict[str, str] = {}
    axis_lines, motor_lines, body = [], [], []
    for line in lines:
        if line.startswith("#") and not body:
            toks = line[1:].split()
            pairs = dict(t.partition("=")[::2] for t in toks if "=" in t)
            if toks and toks[0] == "axis":
                axis_lines.append(pairs)
            elif toks and toks[0] == "motor":
                motor_lines.append(pairs)
            else:
                meta.update(pairs)
                if FORMAT in toks:
                    meta["format"] = FORMAT
        elif line.strip():
            body.append(line)
    if meta.get("format") != FORMAT:
        raise InputError(f"not a compensation table (first comment must name {FORMAT})", file=src)
    fv = _check_format_version(_parse(meta, "format_version", int, src), src)
    reference = None
    if fv >= 2:
        kind = meta.get("kind")
        ref_doc = {"kind": kind}
        if kind == "nominal_ik":
            ref_doc.update({k: _parse(meta, k, float, src) for k in NominalReference.KEYS})
        reference = _reference(ref_doc, src)
    if fv >= 4:
        num = {"min": float, "max": float, "n": int, "max_step": float}
        axes = [_axis({k: _parse(a, k, num.get(k, str), src) for k in _AXIS_KEYS}, src) for a in axis_lines]
        motors = [_motor({k: _parse(m, k, num.get(k, str), src) for k in _MOTOR_KEYS}, src) for m in motor_lines]
    else:
        axes, motors = _legacy(meta, meta, src, lambda d, k, s: _parse(d, k, float, s),
                               lambda d, k, s: _parse(d, k, int, s))
    if not axes or not motors or any(a.n < 1 for a in axes):
        raise InputError("the # header lines need at least one axis and one motor, each axis n >= 1", file=src)
    table = CompTable(machine=meta.get("machine", ""), version=_parse(meta, "table_version", int, src), axes=axes,
                      motors=motors, values=np.zeros(tuple(a.n for a in axes) + (len(motors),)),
                      reference=reference, source=src)
    columns = table.columns()
    if not body or tuple(c.strip() for c in body[0].split(",")) != columns:
        raise InputError(f"header row must be {','.join(columns)}", file=src)
    rows = list(csv.reader(body[1:]))
    n_nodes = int(np.prod(table.shape))
    if len(rows) != n_nodes:
        raise InputError(f"{len(rows)} data rows, header grid {'x'.join(map(str, table.shape))} needs {n_nodes}",
                         file=src, field=columns[0])
    x = table.nodes().reshape(-1, table.n_axes)
    flat = table.values.reshape(-1, table.n_motors)
    for r, row in enumerate(rows, start=1):
        if len(row) != len(columns):
            raise InputError(f"expected {len(columns)} fields, got {len(row)}", file=src, row=r)
        nums = []
        for name, text in zip(columns, row):
            try:
                nums.append(parse_number(text))
            except ValueError:
                raise InputError(f"not a number: {text!r}", file=src, row=r, field=name) from None
        for name, got, want in zip(columns, nums, x[r - 1]):
            if not abs(got - want) <= 1e-9 * max(1.0, abs(want)):
                raise InputError(f"{got:g} is not the grid node {want:.10g} expected at this row (rows go in "
                                 "memory order, last axis fastest)", file=src, row=r, field=name)
        flat[r - 1] = nums[table.n_axes:]
    _check_sums(table, meta, src, fv)
    return table


# ---- helpers ------------------------------------------------------------------------------

def _legacy(grid: dict, lim: dict, src: str, num, integer) -> tuple[list[Axis], list[Motor]]:
    """Formats 1 to 3: axes phi, theta (deg) and motors m1, m2 (deg) sharing one set of limits."""
    axes = [Axis(PHI, "deg", num(grid, "phi_min_deg", src), num(grid, "phi_max_deg", src), integer(grid, "n_phi", src)),
            Axis(THETA, "deg", num(grid, "theta_min_deg", src), num(grid, "theta_max_deg", src),
                 integer(grid, "n_theta", src))]
    m = Motor("m", "deg", num(lim, "m_min_deg", src), num(lim, "m_max_deg", src), num(lim, "max_step_deg", src))
    return axes, [m, m]


def _axis(d: dict, src: str) -> Axis:
    if not isinstance(d["n"], int) or isinstance(d["n"], bool) or d["n"] < 1:
        raise InputError(f"axis {d['name']!r}: n must be a positive integer, got {d['n']!r}", file=src, field="axes")
    if not all(isinstance(d[k], (int, float)) and not isinstance(d[k], bool) for k in ("min", "max")):
        raise InputError(f"axis {d['name']!r}: min and max must be numbers", file=src, field="axes")
    if not all(isinstance(d[k], str) for k in ("name", "unit")):
        raise InputError("axis name and unit must be strings", file=src, field="axes")
    return Axis(d["name"], d["unit"], float(d["min"]), float(d["max"]), d["n"])


def _motor(d: dict, src: str) -> Motor:
    if not all(isinstance(d[k], (int, float)) and not isinstance(d[k], bool) for k in ("min", "max", "max_step")):
        raise InputError(f"motor {d['name']!r}: min, max and max_step must be numbers", file=src, field="motors")
    if d["unit"] not in ("deg", "mm"):
        raise InputError(f"motor {d['name']!r}: unit must be deg or mm, got {d['unit']!r}", file=src, field="motors")
    return Motor(str(d["name"]), d["unit"], float(d["min"]), float(d["max"]), float(d["max_step"]))


def _list(doc: dict, key: str, src: str) -> list:
    v = doc.get(key)
    if not isinstance(v, list) or not all(isinstance(x, dict) for x in v) or not v:
        raise InputError(f"'{key}' must be a non-empty list of objects", file=src, field=key)
    if key == "motors" and len(v) > NMOTOR_MAX:
        raise InputError(f"{len(v)} motors: a table holds 1..{NMOTOR_MAX}", file=src, field=key)
    return v


def _get(d: dict, key: str, src: str, where: str):
    if key not in d:
        raise InputError(f"missing '{key}'", file=src, field=where)
    return d[key]


def _num(x) -> str:
    """Shortest text that reads back to the same double (repr), integers without '.0'."""
    x = float(x)
    if x.is_integer() and abs(x) < 1e15 and np.copysign(1.0, x) > 0:
        return str(int(x))
    return repr(x)


def _check_format_version(v, src: str) -> int:
    """The format version of a file; version 1 (absolute commands) is read as a table without reference."""
    if isinstance(v, bool) or v not in READ_VERSIONS:
        raise InputError(f"format_version {v!r} not supported (this reader knows "
                         f"{', '.join(map(str, READ_VERSIONS))})", file=src, field="format_version")
    return int(v)


def _reference(doc: dict, src: str) -> NominalReference | ControllerReference | None:
    kind = doc.get("kind")
    if kind == "none":
        return None
    if kind == ControllerReference.KIND:
        return CONTROLLER
    if kind != "nominal_ik":
        raise InputError(f"reference kind must be 'nominal_ik', 'controller' or 'none', got {kind!r}", file=src,
                         field="reference")
    ref = NominalReference(**{k: _float(doc, k, src) for k in NominalReference.KEYS})
    if ref.defect():
        raise InputError(ref.defect(), file=src, field="reference")
    return ref


def _section(doc: dict, key: str, src: str) -> dict:
    sec = doc.get(key)
    if not isinstance(sec, dict):
        raise InputError(f"missing section '{key}'", file=src, field=key)
    return sec


def _int(d: dict, key: str, src: str) -> int:
    v = d.get(key)
    if isinstance(v, bool) or not isinstance(v, int):
        raise InputError(f"must be an integer, got {v!r}", file=src, field=key)
    return v


def _float(d: dict, key: str, src: str) -> float:
    v = d.get(key)
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise InputError(f"must be a number, got {v!r}", file=src, field=key)
    return float(v)


def _str(d: dict, key: str, src: str) -> str:
    v = d.get(key)
    if not isinstance(v, str):
        raise InputError(f"must be a string, got {v!r}", file=src, field=key)
    return v


def _parse(meta: dict, key: str, kind: type, src: str):
    if key not in meta:
        raise InputError(f"missing '{key}=' in the # header lines", file=src, field=key)
    try:
        return kind(meta[key]) if kind is str else parse_number(meta[key], kind)
    except ValueError:
        raise InputError(f"bad value {meta[key]!r} in the # header lines", file=src, field=key) from None


def _crc_v3(table: CompTable) -> int:
    """The CRC-32 a format-3 file carries: the 104-byte header of format 3, then the data."""
    ref = table.reference
    p, t = table.axes
    m = table.motors[0]
    head = _HEADER_V3.pack(p.min, p.max, t.min, t.max, m.min, m.max, m.max_step, int(table.version), 3, p.n, t.n,
                           0 if ref is None else 1, 0, 0 if ref is None else ref.crc32(),
                           table.machine.encode("ascii", "replace")[:27])
    return crc32(table.data_bytes(), crc32(head))


def _check_sums(table: CompTable, doc: dict, src: str, format_version: int = FORMAT_VERSION) -> None:
    """Compare the checksums stored in a file with the data read from it; both must be present.

    Formats 3 and 4 carry ``crc32`` (header image of their format, then the data); formats 1 and 2 carry
    ``crc16_ccitt`` (CRC-16/CCITT-FALSE over the data only). A version-1 file's SHA-256 covers the values
    only (it has no reference).
    """
    name = "crc32" if format_version >= 3 else "crc16_ccitt"
    crc_text, sha_text = doc.get(name), doc.get("sha256")
    for key, text in ((name, crc_text), ("sha256", sha_text)):
        if text is None:
            raise InputError(f"no {key} checksum: a table must carry {name} and sha256 "
                             "(write it with pmcal; edited files are refused)", file=src, field=key)
    if not np.isfinite(table.values).all():
        return   # validate() names the bad node; a checksum message would hide it
    bad_version = table.version_defect()
    if bad_version:              # not packable into the header image the CRC covers
        raise InputError(bad_version.message, file=src, field=bad_version.field)
    try:
        crc = int(str(crc_text), 16)
    except ValueError:
        raise InputError(f"bad CRC {crc_text!r}", file=src, field=name) from None
    if format_version >= 4:
        want = table.crc32()
    elif format_version == 3:
        want = _crc_v3(table)
    else:
        want = binascii.crc_hqx(table.data_bytes(), 0xFFFF)
    if crc != want:
        width = 8 if format_version >= 3 else 4
        raise InputError(f"CRC mismatch: file says 0x{crc:0{width}X}, data give 0x{want:0{width}X} "
                         "(file edited or damaged)", file=src, field=name)
    sha = table.sha256() if format_version >= 2 else hashlib.sha256(table.data_bytes()).hexdigest()
    if str(sha_text).lower() != sha:
        raise InputError("SHA-256 mismatch between the file's checksum and its data (file edited or damaged)",
                         file=src, field="sha256")
