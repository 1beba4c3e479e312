"""Reading and writing the project's CSV files (UTF-8, header row, ``#`` comment lines at the top).

Rows are numbered from 1 after the header, as a person sees them; every problem raises
:class:`pmcal.errors.InputError` naming the file, the row and the field.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from pmcal.errors import InputError
from pmcal.fileio import atomic_write, read_text


def parse_number(text: str, kind: type = float) -> float | int:
    """The one reader of a number in a text file: as pmcal's files write it (``-2.5``, ``1e3``, ``7``; blanks
    around it allowed), as ``kind`` (``float`` or ``int``).

    ``ValueError`` for anything else, also for what Python's ``float`` and ``int`` take but no file means:
    digits grouped with ``_`` (``1_000``). ``inf`` and ``nan`` are returned as floats; the callers refuse
    them by name.
    """
    if "_" in text:
        raise ValueError(f"digits grouped with '_' in {text!r}")
    return kind(text)


@dataclass
class CsvTable:
    """A parsed CSV file: header, string rows, comment lines and the file's name (for messages)."""

    path: str
    header: list[str]
    rows: list[list[str]]
    comments: list[str]

    def has(self, column: str) -> bool:
        return column in self.header

    def require(self, columns: Iterable[str]) -> None:
        missing = [c for c in columns if c not in self.header]
        if missing:
            raise InputError(f"missing column{'s' if len(missing) > 1 else ''} {', '.join(missing)}",
                             file=self.path, field=missing[0])

    def text(self, column: str) -> list[str]:
        k = self.header.index(column)
        return [r[k].strip() for r in self.rows]

    def numbers(self, column: str, *, allow_empty: bool = False, default: float = math.nan) -> np.ndarray:
        """A column as floats; a non-number or non-finite value raises naming row and field."""
        k = self.header.index(column)
        out = np.empty(len(self.rows))
        for i, row in enumerate(self.rows):
            cell = row[k].strip()
            if cell == "" and allow_empty:
                out[i] = default
                continue
            try:
                v = parse_number(cell)
            except ValueError:
                raise InputError(f"'{cell}' is not a number" + (" (write it without '_')" if "_" in cell else ""),
                                 file=self.path, row=i + 1, field=column) from None
            if not math.isfinite(v):
                raise InputError(f"value '{cell}' is not finite", file=self.path, row=i + 1, field=column)
            out[i] = v
        return out

    def unique_ids(self, column: str) -> list[str]:
        ids = self.text(column)
        seen: dict[str, int] = {}
        for i, v in enumerate(ids):
            if v == "":
                raise InputError("empty id", file=self.path, row=i + 1, field=column)
            if v in seen:
                raise InputError(f"duplicate id '{v}' (first at row {seen[v]})", file=self.path, row=i + 1,
                                 field=column)
            seen[v] = i + 1
        return ids


#: largest CSV file read, bytes: far above any measurement campaign (100 000 poses of 3 targets are ~10 MB)
MAX_CSV_BYTES = 64 * 1024 * 1024


def read_csv(path: str | Path, max_rows: int | None = None) -> CsvTable:
    """Read a CSV file with optional leading ``#`` comment lines; at most ``max_rows`` data rows."""
    p = str(path)
    try:
        if Path(path).is_file() and Path(path).stat().st_size > MAX_CSV_BYTES:
            raise InputError(f"{Path(path).stat().st_size / 2**20:.0f} MiB, larger than the "
                             f"{MAX_CSV_BYTES // 2**20} MiB a pmcal CSV may have (docs/formats.md, 'Size "
                             "limits'): split the file or thin it out", file=p)
    except OSError as exc:
        raise InputError(f"cannot read file ({exc.strerror or exc})", file=p) from None
    raw = read_text(path)
    lines = raw.splitlines()
    comments = []
    while lines and (lines[0].lstrip().startswith("#") or not lines[0].strip()):
        comments.append(lines.pop(0).lstrip()[1:].strip() if lines[0].strip() else "")
    if not lines:
        raise InputError("no header row", file=p)
    reader = csv.reader(io.StringIO("\n".join(lines)))
    header = [h.strip() for h in next(reader)]
    for sep, name in ((";", "semicolons"), ("\t", "tabs")):
        if len(header) == 1 and sep in lines[0]:
            raise InputError(f"the columns are separated by {name}: pmcal reads comma-separated CSV (save it "
                             "with ',' as the separator and '.' as the decimal point)", file=p)
    if len(set(header)) != len(header):
        dup = next(h for h in header if header.count(h) > 1)
        raise InputError("duplicate column", file=p, field=dup)
    rows = []
    for i, row in enumerate(reader):
        if not any(c.strip() for c in row):
            continue
        if max_rows is not None and len(rows) >= max_rows:
            n = len(rows) + 1 + sum(1 for r in reader if any(c.strip() for c in r))
            raise InputError(f"{n} data rows, more than the {max_rows} this command reads "
                             f"(docs/formats.md, 'Size limits'): split the file or thin it out to at most "
                             f"{max_rows} rows", file=p)
        if len(row) != len(header):
            raise InputError(f"{len(row)} fields where the header has {len(header)}", file=p, row=len(rows) + 1)
        rows.append(row)
    if not rows:
        raise InputError("no data rows", file=p)
    return CsvTable(path=p, header=header, rows=rows, comments=[c for c in comments if c])


#: Most poses a measurement file may hold: identification and diagnosis solve dense problems whose cost
#: grows with the poses (a campaign has 24..128; 2000 take minutes).
MAX_POSES = 2000
#: Above this many poses identify and diagnose take long (tens of seconds to minutes): they report their
#: steps on stderr also when piped (:func:`pmcal.progress.set_long`).
LONG_POSES = 200
#: coordinates of a tracker target, in column order
TARGET_AXES = ("x", "y", "z")


def target_columns(k: int) -> list[str]:
    """Columns of ``k`` tracker targets: ``t1_x, t1_y, t1_z, ..., tk_z`` (mm)."""
    return [f"t{i}_{a}" for i in range(1, k + 1) for a in TARGET_AXES]


def check_context(path: str, approach: np.ndarray | None = None, temp_c: np.ndarray | None = None,
                  temp_field: str = "temp_c", payload_kg: np.ndarray | None = None) -> None:
    """The context columns of a measurement or campaign file (those given): approach signs +1 / -1 only; a
    temperature for every row or for none, within 20 +- 60 degC (a value outside is degrees Fahrenheit or
    kelvin); no negative payload. An :class:`InputError` names file, row and field."""
    if payload_kg is not None and np.any(payload_kg < 0):
        raise InputError("payload must not be negative", file=path, row=int(np.flatnonzero(payload_kg < 0)[0]) + 1,
                         field="payload_kg")
    if approach is not None:
        bad = np.argwhere(~np.isin(approach, (-1.0, 1.0)))
        if bad.size:
            i, j = (int(v) for v in bad[0])
            raise InputError(f"approach must be +1 or -1, got {approach[i, j]:g}", file=path, row=i + 1,
                             field=f"m{j + 1}_approach")
    if temp_c is not None:
        bad = np.flatnonzero(~np.isfinite(temp_c))
        if 0 < bad.size < len(temp_c):
            raise InputError("temperature missing in some rows (give it for every pose or for none)",
                             file=path, row=int(bad[0]) + 1, field=temp_field)
        far = np.flatnonzero(np.abs(temp_c - 20.0) > 60.0)
        if far.size:
            raise InputError(f"temperature {temp_c[far[0]]:g} degC is implausible for a machine in use "
                             "(degrees Fahrenheit or kelvin?)", file=path, row=int(far[0]) + 1, field=temp_field)


#: Largest plausible error of a measured distance between two targets (mm).
PLAUSIBLE_TARGET_DISTANCE_MM = 2.0
#: The same in the tracker frame, where gross outliers are expected and rejected (named) by the robust fit:
#: only a unit mix-up or a swapped column is an input error there (mm); also the limit of ``pmcal import``,
#: which does not know the frame yet.
PLAUSIBLE_TARGET_DISTANCE_TRACKER_MM = 20.0


def check_nest_distances(targets: np.ndarray, nominal: np.ndarray, path: str, limit_mm: float) -> None:
    """The distances between the measured targets of each row against the machine's nest geometry.

    Parameters
    ----------
    targets : ndarray, shape (n, k, 3)
        Measured nest positions, mm, any frame (NaN: a blocked target, skipped).
    nominal : ndarray, shape (k, 3) or (n, k, 3)
        The nests on the nominal machine, mm: on the platform, or where the nominal machine puts them at each
        row's commands (NaN: a row it cannot assemble, skipped).
    path : str
        The file named in the error.
    limit_mm : float
        Largest accepted difference of a measured distance from the nominal one, mm.

    Raises
    ------
    pmcal.errors.InputError
        Naming the first row and pair beyond ``limit_mm`` (field ``tB_x``; values in metres said so).
    """
    k = targets.shape[1]
    pairs = [(a, b) for a in range(k) for b in range(a + 1, k)]
    if not pairs:
        return
    nominal = np.broadcast_to(nominal, targets.shape)
    d_nom = np.stack([np.linalg.norm(nominal[:, a] - nominal[:, b], axis=1) for a, b in pairs], 1)
    d_meas = np.stack([np.linalg.norm(targets[:, a] - targets[:, b], axis=1) for a, b in pairs], 1)
    bad = np.abs(d_meas - d_nom) > limit_mm
    if bad.any():
        row, p = np.argwhere(bad)[0]
        a, b = pairs[p]
        ratio = d_meas[row, p] / d_nom[row, p]
        hint = " (values look like metres: the file must be in mm)" if 5e-4 < ratio < 2e-3 else ""
        raise InputError(f"targets t{a + 1} and t{b + 1} are {d_meas[row, p]:.4g} mm apart, the platform "
                         f"has them {d_nom[row, p]:.4g} mm apart{hint}", file=path, row=int(row) + 1,
                         field=f"t{b + 1}_x")


def check_time_order(time_s: np.ndarray, path: str, field: str = "time_s") -> None:
    """Time stamps (s) of rows in measurement order: never decreasing (equal stamps allowed: a clock of 1 s
    steps gives them). An :class:`InputError` names the first row whose time is earlier than the row's before."""
    for i in np.flatnonzero(np.diff(time_s) < 0)[:1]:
        raise InputError(f"time goes backwards ({time_s[i + 1]:g} s after {time_s[i]:g} s): the rows are the "
                         "measurement order", file=path, row=int(i) + 2, field=field)


def check_blocked(coords: np.ndarray, path: str, min_visible: int = 2) -> None:
    """Blocked targets (all three cells empty, NaN in ``coords`` of shape (n, k, 3)) are allowed; a
    half-empty target or a row with fewer than ``min_visible`` measured targets is an :class:`InputError`
    naming row and field."""
    empty = np.isnan(coords)
    for i, j in np.argwhere(empty.any(axis=2) & ~empty.all(axis=2)):
        a = TARGET_AXES[int(np.flatnonzero(empty[i, j])[0])]
        raise InputError(f"target t{j + 1} is half empty: leave all three of t{j + 1}_x, t{j + 1}_y, "
                         f"t{j + 1}_z empty for a blocked target", file=path, row=int(i) + 1, field=f"t{j + 1}_{a}")
    n_vis = (~empty.all(axis=2)).sum(axis=1)
    for i in np.flatnonzero(n_vis < min_visible):
        j = int(np.flatnonzero(empty[i].all(axis=1))[0])
        raise InputError(f"only {n_vis[i]} target(s) measured: a row needs at least {min_visible}", file=path,
                         row=int(i) + 1, field=f"t{j + 1}_x")


def write_columns(path: str | Path, id_column: str, ids: Sequence[str], columns: Sequence[tuple[str, np.ndarray, str]],
                  comments: Sequence[str] = ()) -> None:
    """Write a CSV of one id column and numeric ``columns`` (name, values, format), atomically; NaN is an
    empty cell (a blocked target, a missing value)."""
    header = [id_column] + [name for name, _, _ in columns]
    rows = ([pid] + ["" if math.isnan(float(v[i])) else f.format(float(v[i])) for _, v, f in columns]
            for i, pid in enumerate(ids))
    write_csv(path, header, rows, comments)


def write_csv(path: str | Path, header: Sequence[str], rows: Iterable[Sequence], comments: Sequence[str] = (),
              float_format: str = "{:.6f}") -> None:
    """Write a CSV atomically; floats with ``float_format``, comments as leading ``#`` lines."""
    def cell(v):
        if isinstance(v, (float, np.floating)):
            return float_format.format(float(v))
        return str(v)

    with atomic_write(path) as fh:
        for c in comments:
            fh.write(f"# {c}\n")
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(header)
        for row in rows:
            w.writerow([cell(v) for v in row])
