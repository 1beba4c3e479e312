"""The compensation table: a 2-D grid over target orientation holding corrected motor commands.

Format specification: ``docs/compensation_table.md``. Units: degrees everywhere in this module (it is
an interface type, written to files and sent to the PLC).

The grid spans ``phi_deg`` (azimuth) from ``phi_min_deg`` to ``phi_max_deg`` in ``n_phi`` nodes and
``theta_deg`` (tilt) from ``theta_min_deg`` to ``theta_max_deg`` in ``n_theta`` nodes, both ends
included. ``values[i, j, k]`` is, for motor ``k`` (0: m1, 1: m2) in degrees, the correction to add to
the nominal closed-form inverse kinematics (``reference``, :mod:`pmcal.bridge.nominal`, format version 2)
so that the calibrated machine reaches (phi_i, theta_j); with ``reference=None`` it is the absolute
command (format version 1 semantics). The array layout is the PLC's memory layout
``ARRAY[0..NPHI_MAX-1, 0..NTHETA_MAX-1, 0..1] OF LREAL`` restricted to the used nodes (last index
fastest, little-endian IEEE-754 double).

Longer than the project's ~400 lines on purpose: the type, its checks and its two file formats
(JSON, CSV, versions 1 and 2) form one interface specification with docs/compensation_table.md.

Typical use by the identification code::

    table = CompTable.from_setpoints(my_setpoints, machine="ocpm_2dof", version=7,
                                     n_phi=73, n_theta=31, motor_limits_deg=(-120.0, 60.0))
    table.validate()
    table.save("comp.json")          # JSON plus comp.csv beside it, both written atomically
"""

from __future__ import annotations

import binascii
import csv
import hashlib
import json
import math
import struct
import zlib
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Callable, NamedTuple

import numpy as np

from pmcal.bridge.nominal import NominalReference
from pmcal.errors import InputError
from pmcal.fileio import atomic_write

FORMAT = "pmcal-comptable"
#: 3: CRC-32 over the PLC header image and the data (``crc32``); 2 (read): CRC-16 over the data only;
#: 1 (read, converted): absolute commands. Values relative to the nominal IK (``reference``) since 2.
FORMAT_VERSION = 3
READ_VERSIONS = (1, 2, 3)
#: fixed PLC array sizes (ARRAY[0..NPHI_MAX-1, 0..NTHETA_MAX-1, 0..1] OF LREAL)
NPHI_MAX = 100
NTHETA_MAX = 100
#: table versions are UDINT on the PLC; 0 means "no table"
VERSION_MAX = 2**32 - 1
#: STRING(27) on the PLC
MACHINE_MAX_LEN = 27
#: largest azimuth span (deg); the PLC never wraps phi, so a table covers at most one turn
PHI_SPAN_MAX_DEG = 360.0
#: largest magnitude of a grid limit, motor limit or max step (deg): GVL_CompTableParam.LIMIT_ABS_MAX, so
#: every difference the PLC forms between limits or commands stays finite
LIMIT_ABS_MAX_DEG = 1.0e6
#: ST_CompTableHeader, 104 bytes (pack_mode 1, naturally aligned): fPhiMin .. fMaxStep (7 LREAL),
#: nTableVersion UDINT, nFormatVersion, nPhi, nTheta, nReference UINT, nCrc, nReferenceCrc DWORD,
#: sMachine STRING(27)
HEADER_STRUCT = struct.Struct("<7dI4H2I28s")
CSV_COLUMNS = ("phi_deg", "theta_deg", "m1_deg", "m2_deg")
#: CSV columns of a table with a nominal-IK reference (the values are corrections)
CSV_COLUMNS_REF = ("phi_deg", "theta_deg", "dm1_deg", "dm2_deg")
MOTOR_FIELDS = ("m1_deg", "m2_deg")

Setpoints = Callable[[np.ndarray, np.ndarray], np.ndarray]


def crc32(data: bytes, crc: int = 0) -> int:
    """CRC-32 (IEEE 802.3, reflected polynomial 0xEDB88320, init and final XOR 0xFFFFFFFF) as the PLC's
    ``F_CompTableCrc32(pData, cbData, nCrc := 0)`` computes it; ``zlib.crc32``.

    Check value: ``crc32(b"123456789") == 0xCBF43926``. Chainable like the PLC function:
    ``crc32(b, crc32(a)) == crc32(a + b)``.
    """
    return zlib.crc32(data, crc)


def pack_header(limits: dict, *, version: int, format_version: int, n_phi: int, n_theta: int, reference: int,
                crc: int, reference_crc: int, machine: str) -> bytes:
    """The ST_CompTableHeader image (:data:`HEADER_STRUCT`); ``limits`` in :class:`GridLimits` order."""
    name = machine.encode("ascii", "replace")[:MACHINE_MAX_LEN]
    return HEADER_STRUCT.pack(*limits.values(), version, format_version, n_phi, n_theta, reference, crc,
                              reference_crc, name)


class Defect(NamedTuple):
    """The first thing wrong with a table: what kind, a message, where (node and motor field)."""

    kind: str          # grid_size, grid_limits, limits, version, machine, not_finite, out_of_range, step
    message: str
    node: tuple[int, int] | None = None
    field: str | None = None


def bilinear(values: np.ndarray, phi_lim: tuple[float, float], theta_lim: tuple[float, float],
             phi_deg, theta_deg) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear interpolation on a grid, with exactly the arithmetic of ``FB_CompTableLookup`` (ST).

    ``values`` is (n_phi, n_theta, 2) in deg; ``phi_deg``/``theta_deg`` broadcast together.
    Returns ``(m_deg, inside)``: ``m_deg`` of shape (..., 2) and a boolean mask of the points inside
    the grid (outside points get NaN). Per point, in IEEE double, in this order::

        u  := (phi - phi_min) / (phi_max - phi_min) * (n_phi - 1)
        i  := MIN(TRUNC(u), n_phi - 2);   fu := u - i          (same for theta: v, j, fv)
        a  := A[i,j]   + (A[i+1,j]   - A[i,j])   * fu
        b  := A[i,j+1] + (A[i+1,j+1] - A[i,j+1]) * fu
        m  := a + (b - a) * fv
    """
    phi, theta = np.broadcast_arrays(np.asarray(phi_deg, dtype=np.float64),
                                     np.asarray(theta_deg, dtype=np.float64))
    n_phi, n_theta = values.shape[0], values.shape[1]
    inside = ((phi >= phi_lim[0]) & (phi <= phi_lim[1])
              & (theta >= theta_lim[0]) & (theta <= theta_lim[1]))
    p = np.where(inside, phi, phi_lim[0])
    t = np.where(inside, theta, theta_lim[0])
    u = (p - phi_lim[0]) / (phi_lim[1] - phi_lim[0]) * float(n_phi - 1)
    v = (t - theta_lim[0]) / (theta_lim[1] - theta_lim[0]) * float(n_theta - 1)
    i = np.minimum(np.trunc(u), n_phi - 2).astype(np.intp)
    j = np.minimum(np.trunc(v), n_theta - 2).astype(np.intp)
    fu = (u - i)[..., None]
    fv = (v - j)[..., None]
    a00, a10 = values[i, j], values[i + 1, j]
    a01, a11 = values[i, j + 1], values[i + 1, j + 1]
    a = a00 + (a10 - a00) * fu
    b = a01 + (a11 - a01) * fu
    m = a + (b - a) * fv
    m[~inside] = np.nan
    return m, inside


@dataclass
class GridLimits:
    """Grid span and motor limits of a table, deg (shared by :class:`CompTable` and the PLC header)."""

    phi_min_deg: float
    phi_max_deg: float
    theta_min_deg: float
    theta_max_deg: float
    m_min_deg: float
    m_max_deg: float
    max_step_deg: float

    def limits(self) -> dict[str, float]:
        """The seven limits as keyword arguments."""
        return {f.name: getattr(self, f.name) for f in fields(GridLimits)}


@dataclass(eq=False, kw_only=True)
class CompTable(GridLimits):
    """A compensation table (deg). ``values`` has shape (n_phi, n_theta, 2): m1_deg, m2_deg per node.

    Keyword-only. ``version`` is the table version (UDINT, 1..2**32-1) that the PLC requires to increase
    strictly. ``max_step_deg`` bounds the change of either motor command between neighbouring nodes.
    ``reference``: the nominal IK the values are corrections to (None: values are absolute commands).
    ``source`` (not part of the data) names the file the table was read from, for error messages.
    """

    machine: str
    version: int
    values: np.ndarray
    reference: NominalReference | None = None
    source: str | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        self.values = np.ascontiguousarray(self.values, dtype="<f8")
        if self.values.ndim != 3 or self.values.shape[2] != 2:
            raise InputError(f"table values must have shape (n_phi, n_theta, 2), got {self.values.shape}",
                             file=self.source, field="values")
        for name, value in self.limits().items():
            setattr(self, name, float(value))

    # ---- geometry -------------------------------------------------------------------------
    @property
    def n_phi(self) -> int:
        return int(self.values.shape[0])

    @property
    def n_theta(self) -> int:
        return int(self.values.shape[1])

    def phi_nodes_deg(self) -> np.ndarray:
        """Azimuth of the grid rows, deg (both ends included)."""
        return _nodes(self.phi_min_deg, self.phi_max_deg, self.n_phi)

    def theta_nodes_deg(self) -> np.ndarray:
        """Tilt of the grid columns, deg (both ends included)."""
        return _nodes(self.theta_min_deg, self.theta_max_deg, self.n_theta)

    def with_version(self, version: int) -> "CompTable":
        """A copy with another table version (values shared, read-only use)."""
        return replace(self, version=int(version))

    # ---- checksums ------------------------------------------------------------------------
    def data_bytes(self) -> bytes:
        """The used nodes as the PLC stores them row by row: little-endian doubles, C order."""
        return self.values.tobytes(order="C")

    def nominal_at_nodes(self) -> np.ndarray:
        """The reference commands (n_phi, n_theta, 2) deg at the nodes; zeros without reference."""
        if self.reference is None:
            return np.zeros_like(self.values)
        pp, tt = np.meshgrid(self.phi_nodes_deg(), self.theta_nodes_deg(), indexing="ij")
        return self.reference.commands_deg(pp, tt)

    def commands_at_nodes(self) -> np.ndarray:
        """Absolute motor commands (n_phi, n_theta, 2) deg at the nodes: reference + correction."""
        return self.values if self.reference is None else self.nominal_at_nodes() + self.values

    def header_bytes(self, crc: int = 0) -> bytes:
        """The PLC header image of this table (ST_CompTableHeader) with ``nCrc = crc``."""
        ref = self.reference
        return pack_header(self.limits(), version=int(self.version), format_version=FORMAT_VERSION,
                           n_phi=self.n_phi, n_theta=self.n_theta, reference=0 if ref is None else 1, crc=crc,
                           reference_crc=0 if ref is None else ref.crc32(), machine=self.machine)

    def crc32(self) -> int:
        """CRC-32 (:func:`crc32`) over :meth:`header_bytes` with ``nCrc = 0``, then :meth:`data_bytes`
        (the used nodes row by row): what the PLC recomputes over its copy before using the table."""
        return crc32(self.data_bytes(), crc32(self.header_bytes(0)))

    def sha256(self) -> str:
        """SHA-256 (hex) over :meth:`data_bytes` followed by the reference geometry's five LREALs
        (:meth:`NominalReference.pack`, nothing without a reference), for the files and the audit trail."""
        ref = b"" if self.reference is None else self.reference.pack()
        return hashlib.sha256(self.data_bytes() + ref).hexdigest()

    # ---- validation -----------------------------------------------------------------------
    def defect(self, active_version: int | None = None) -> Defect | None:
        """The first defect in the order the PLC checks (header, then data), or None.

        ``active_version``: the version active on the PLC; this table must be strictly newer.
        """
        return self.header_defect(active_version) or self.data_defect()

    def header_defect(self, active_version: int | None = None) -> Defect | None:
        """Grid size and limits, motor limits and max step, version range and recency, machine name."""
        if not (2 <= self.n_phi <= NPHI_MAX and 2 <= self.n_theta <= NTHETA_MAX):
            return Defect("grid_size", f"grid {self.n_phi}x{self.n_theta} outside 2x2..{NPHI_MAX}x{NTHETA_MAX}")
        if self.reference is not None and self.reference.defect():
            return Defect("reference", self.reference.defect())
        grid = (self.phi_min_deg, self.phi_max_deg, self.theta_min_deg, self.theta_max_deg)
        if not all(math.isfinite(g) and abs(g) <= LIMIT_ABS_MAX_DEG for g in grid):
            return Defect("grid_limits", f"grid limits must be finite, at most {LIMIT_ABS_MAX_DEG:g} deg in size")
        if not (self.phi_min_deg < self.phi_max_deg and self.theta_min_deg < self.theta_max_deg):
            return Defect("grid_limits", "grid limits must increase (phi_min < phi_max, theta_min < theta_max)")
        if self.phi_max_deg - self.phi_min_deg > PHI_SPAN_MAX_DEG:
            return Defect("grid_limits", f"phi span exceeds {PHI_SPAN_MAX_DEG:g} deg")
        lims = (self.m_min_deg, self.m_max_deg, self.max_step_deg)
        if not (all(math.isfinite(x) and abs(x) <= LIMIT_ABS_MAX_DEG for x in lims)
                and self.m_min_deg < self.m_max_deg and self.max_step_deg > 0.0):
            return Defect("limits", f"motor limits and max_step must be finite, at most {LIMIT_ABS_MAX_DEG:g} deg "
                                    "in size, with m_min < m_max and max_step > 0")
        if not (isinstance(self.version, (int, np.integer)) and 1 <= int(self.version) <= VERSION_MAX):
            return Defect("version", f"table version {self.version!r} outside 1..{VERSION_MAX}")
        if active_version is not None and int(self.version) <= int(active_version):
            return Defect("stale_version", f"table version {self.version} is not newer than the active "
                                           f"version {active_version} on the PLC")
        if not (self.machine.isascii() and 0 < len(self.machine) <= MACHINE_MAX_LEN):
            return Defect("machine", f"machine name must be 1..{MACHINE_MAX_LEN} ASCII characters")
        return None

    def data_defect(self) -> Defect | None:
        """All values finite, then all within the motor limits, then every step within max_step.

        Limits and steps apply to the absolute commands (reference + correction) at the nodes.
        Each check covers the whole table before the next starts (as FB_CompTableCheck's phases).
        """
        bad = ~np.isfinite(self.values)
        if bad.any():
            return self._node_defect("not_finite", bad, "is not a finite number")
        v = self.commands_at_nodes()
        bad = ~np.isfinite(v)
        if bad.any():
            return self._node_defect("not_finite", bad, "gives a nominal command out of reach")
        bad = (v < self.m_min_deg) | (v > self.m_max_deg)
        if bad.any():
            return self._node_defect("out_of_range", bad, f"outside the motor limits "
                                     f"[{self.m_min_deg:g}, {self.m_max_deg:g}] deg")
        for axis, name in ((0, "phi"), (1, "theta")):
            step = np.abs(np.diff(v, axis=axis))
            bad = step > self.max_step_deg
            if bad.any():
                i, j, k = (int(x) for x in np.argwhere(bad)[0])
                nxt = (i + 1, j) if axis == 0 else (i, j + 1)
                return Defect("step", f"step of {step[i, j, k]:.6g} deg to the next node along {name} "
                                      f"{nxt} exceeds max_step {self.max_step_deg:g} deg", (i, j), MOTOR_FIELDS[k])
        return None

    def validate(self, active_version: int | None = None) -> "CompTable":
        """Raise :class:`InputError` naming file, row (CSV node row) and field on the first defect.

        Checks: grid size (2..100 each way), grid and motor limits, version range (and newer than
        ``active_version`` when given), finiteness, motor range, steps between neighbours, machine
        name. Returns ``self`` so calls chain.
        """
        d = self.defect(active_version)
        if d is None:
            return self
        if d.node is None:
            raise InputError(d.message, file=self.source, field=d.field)
        i, j = d.node
        where = (f"node ({i}, {j}) at phi={self.phi_nodes_deg()[i]:.6g} deg, "
                 f"theta={self.theta_nodes_deg()[j]:.6g} deg: ")
        raise InputError(where + d.message, file=self.source, row=i * self.n_theta + j + 1, field=d.field)

    def _node_defect(self, kind: str, bad: np.ndarray, what: str) -> Defect:
        i, j, k = (int(x) for x in np.argwhere(bad)[0])
        if self.reference is None or kind == "not_finite":
            text = f"{MOTOR_FIELDS[k]} = {float(self.values[i, j, k])!r} {what}"
        else:
            text = (f"command {MOTOR_FIELDS[k]} = nominal + correction "
                    f"{float(self.values[i, j, k])!r} = {float(self.commands_at_nodes()[i, j, k])!r} {what}")
        return Defect(kind, text, (i, j), MOTOR_FIELDS[k])

    # ---- evaluation -----------------------------------------------------------------------
    def interpolate(self, phi_deg, theta_deg) -> np.ndarray:
        """Motor commands (..., 2) in deg at target orientations, as FB_CompTableLookup on the PLC.

        ``reference(phi, theta) + bilinear(values)`` (bilinear alone without reference), in that
        order of IEEE operations. Raises :class:`InputError` if a target lies outside the grid (the
        PLC refuses it too).
        """
        m, inside = lookup(self.values, self.reference, (self.phi_min_deg, self.phi_max_deg),
                           (self.theta_min_deg, self.theta_max_deg), phi_deg, theta_deg)
        if not inside.all():
            raise InputError(f"target orientation outside the table grid phi [{self.phi_min_deg:g}, "
                             f"{self.phi_max_deg:g}] deg, theta [{self.theta_min_deg:g}, {self.theta_max_deg:g}] deg",
                             file=self.source)
        return m

    @classmethod
    def from_setpoints(cls, setpoints: Setpoints, *, machine: str, version: int, n_phi: int = 73,
                       n_theta: int = 31, phi_range_deg: tuple[float, float] = (0.0, 360.0),
                       theta_range_deg: tuple[float, float] = (0.0, 60.0),
                       motor_limits_deg: tuple[float, float] = (-180.0, 180.0),
                       max_step_deg: float = 10.0,
                       reference: NominalReference | str | None = "nominal_ik") -> "CompTable":
        """Fill a table from ``setpoints(phi_deg[N], theta_deg[N]) -> m_deg[N, 2]``.

        The callable receives the N = n_phi*n_theta node coordinates (deg) in row order
        (phi outer, theta inner) and returns the corrected (absolute) motor commands (deg). The table
        stores them relative to ``reference``: ``"nominal_ik"`` (default) is the machine's nominal
        closed-form IK (:meth:`NominalReference.default`), a :class:`NominalReference` another
        geometry, ``None`` absolute commands (the version-1 scheme). Not validated.
        """
        if isinstance(reference, str):
            if reference != "nominal_ik":
                raise ValueError(f"reference must be 'nominal_ik', a NominalReference or None, got {reference!r}")
            reference = NominalReference.default()
        phi = _nodes(*phi_range_deg, n_phi)
        theta = _nodes(*theta_range_deg, n_theta)
        pp, tt = np.meshgrid(phi, theta, indexing="ij")
        m = np.asarray(setpoints(pp.ravel(), tt.ravel()), dtype=np.float64)
        if m.shape != (pp.size, 2):
            raise ValueError(f"setpoints returned shape {m.shape}, expected ({pp.size}, 2)")
        m = m.reshape(n_phi, n_theta, 2)
        if reference is not None:
            m = m - reference.commands_deg(pp, tt)
        return cls(machine=machine, version=int(version), phi_min_deg=phi_range_deg[0],
                   phi_max_deg=phi_range_deg[1], theta_min_deg=theta_range_deg[0],
                   theta_max_deg=theta_range_deg[1], m_min_deg=motor_limits_deg[0],
                   m_max_deg=motor_limits_deg[1], max_step_deg=max_step_deg, values=m, reference=reference)

    # ---- files ----------------------------------------------------------------------------
    def header_dict(self) -> dict:
        """Header fields as written to JSON (also the CSV comment block)."""
        return {
            "format": FORMAT, "format_version": FORMAT_VERSION, "machine": self.machine,
            "table_version": int(self.version),
            "grid": {"n_phi": self.n_phi, "n_theta": self.n_theta,
                     "phi_min_deg": self.phi_min_deg, "phi_max_deg": self.phi_max_deg,
                     "theta_min_deg": self.theta_min_deg, "theta_max_deg": self.theta_max_deg},
            "limits": {"m_min_deg": self.m_min_deg, "m_max_deg": self.m_max_deg,
                       "max_step_deg": self.max_step_deg},
            "reference": {"kind": "none"} if self.reference is None else self.reference.as_dict(),
            "crc32": f"0x{self.crc32():08X}", "sha256": self.sha256(),
        }

    def to_json(self, path: str | Path) -> None:
        """Write the JSON file atomically (header, nested ``values[i][j] = [m1, m2]``, checksums)."""
        doc = self.header_dict()
        doc["layout"] = ("values[i_phi][i_theta] = [m1_deg, m2_deg]; node = min + index*(max-min)/(n-1)"
                         if self.reference is None else
                         "values[i_phi][i_theta] = [dm1_deg, dm2_deg] added to the nominal IK of 'reference'; "
                         "node = min + index*(max-min)/(n-1)")
        doc["values"] = self.values.tolist()
        try:
            text = json.dumps(doc, indent=1, allow_nan=False)
        except ValueError:
            raise InputError("table holds NaN or infinite values; not written", file=str(path),
                             field="values") from None
        with atomic_write(path) as fh:
            fh.write(text + "\n")

    def to_csv(self, path: str | Path) -> None:
        """Write the CSV atomically: ``#`` header lines, then one row per node in memory order."""
        h = self.header_dict()
        g, lim = h["grid"], h["limits"]
        with atomic_write(path) as fh:
            fh.write(f"# {FORMAT} format_version={FORMAT_VERSION}\n")
            fh.write(f"# machine={self.machine}\n# table_version={self.version}\n")
            fh.write("# grid " + " ".join(f"{k}={_num(v)}" for k, v in g.items()) + "\n")
            fh.write("# limits " + " ".join(f"{k}={_num(v)}" for k, v in lim.items()) + "\n")
            fh.write("# reference " + " ".join(f"{k}={v if k == 'kind' else _num(v)}"
                                               for k, v in h["reference"].items()) + "\n")
            fh.write(f"# crc32={h['crc32']} sha256={h['sha256']}\n")
            w = csv.writer(fh, lineterminator="\n")
            w.writerow(CSV_COLUMNS if self.reference is None else CSV_COLUMNS_REF)
            phi, theta = self.phi_nodes_deg(), self.theta_nodes_deg()
            for i in range(self.n_phi):
                for j in range(self.n_theta):
                    w.writerow((_num(phi[i]), _num(theta[j]), _num(self.values[i, j, 0]),
                                _num(self.values[i, j, 1])))

    def save(self, json_path: str | Path) -> tuple[Path, Path]:
        """Write ``json_path`` and the CSV beside it (same stem, ``.csv``); returns both paths."""
        jp = Path(json_path)
        cp = jp.with_suffix(".csv")
        self.to_json(jp)
        self.to_csv(cp)
        return jp, cp

    @classmethod
    def load(cls, path: str | Path) -> "CompTable":
        """Read a table from ``.json`` or ``.csv`` (by suffix)."""
        p = Path(path)
        if p.suffix.lower() == ".csv":
            return cls.from_csv(p)
        return cls.from_json(p)

    @classmethod
    def from_json(cls, path: str | Path) -> "CompTable":
        """Read and check the JSON file (structure, grid shape, checksums); values not validated."""
        src = str(path)
        try:
            doc = json.loads(Path(path).read_text(encoding="utf-8-sig"))
        except FileNotFoundError:
            raise InputError("file not found", file=src) from None
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise InputError(f"not a JSON file: {exc}", file=src) from None
        if not isinstance(doc, dict) or doc.get("format") != FORMAT:
            raise InputError(f"not a compensation table (expected \"format\": \"{FORMAT}\")", file=src,
                             field="format")
        fv = _check_format_version(doc.get("format_version"), src)
        grid, lim = _section(doc, "grid", src), _section(doc, "limits", src)
        reference = None if fv == 1 else _reference(_section(doc, "reference", src), src)
        n_phi, n_theta = _int(grid, "n_phi", src), _int(grid, "n_theta", src)
        try:
            values = np.asarray(doc.get("values"), dtype=np.float64)
        except (TypeError, ValueError):
            raise InputError("values must be numbers nested [n_phi][n_theta][2]", file=src, field="values") from None
        if values.shape != (n_phi, n_theta, 2):
            raise InputError(f"values have shape {values.shape}, header says ({n_phi}, {n_theta}, 2)",
                             file=src, field="values")
        table = cls(machine=_str(doc, "machine", src), version=_int(doc, "table_version", src),
                    phi_min_deg=_float(grid, "phi_min_deg", src), phi_max_deg=_float(grid, "phi_max_deg", src),
                    theta_min_deg=_float(grid, "theta_min_deg", src),
                    theta_max_deg=_float(grid, "theta_max_deg", src),
                    m_min_deg=_float(lim, "m_min_deg", src), m_max_deg=_float(lim, "m_max_deg", src),
                    max_step_deg=_float(lim, "max_step_deg", src), values=values, reference=reference,
                    source=src)
        _check_sums(table, doc, src, fv)
        return table

    @classmethod
    def from_csv(cls, path: str | Path) -> "CompTable":
        """Read and check the CSV file (header comments, node coordinates, checksums)."""
        src = str(path)
        try:
            lines = Path(path).read_text(encoding="utf-8-sig").splitlines()
        except FileNotFoundError:
            raise InputError("file not found", file=src) from None
        except UnicodeDecodeError:
            raise InputError("not a UTF-8 text file", file=src) from None
        meta: dict[str, str] = {}
        body = []
        for line in lines:
            if line.startswith("#") and not body:
                for tok in line[1:].split():
                    if "=" in tok:
                        k, _, v = tok.partition("=")
                        meta[k] = v
                    elif tok == FORMAT:
                        meta["format"] = FORMAT
            elif line.strip():
                body.append(line)
        if meta.get("format") != FORMAT:
            raise InputError(f"not a compensation table (first comment must name {FORMAT})", file=src)
        fv = _check_format_version(_parse(meta, "format_version", int, src), src)
        n_phi, n_theta = _parse(meta, "n_phi", int, src), _parse(meta, "n_theta", int, src)
        reference = None
        if fv >= 2:
            kind = meta.get("kind")
            ref_doc = {"kind": kind}
            if kind == "nominal_ik":
                ref_doc.update({k: _parse(meta, k, float, src) for k in NominalReference.KEYS})
            reference = _reference(ref_doc, src)
        columns = CSV_COLUMNS if reference is None else CSV_COLUMNS_REF
        if not body or tuple(c.strip() for c in body[0].split(",")) != columns:
            raise InputError(f"header row must be {','.join(columns)}", file=src)
        rows = list(csv.reader(body[1:]))
        if len(rows) != n_phi * n_theta or n_phi < 1 or n_theta < 1:
            raise InputError(f"{len(rows)} data rows, header grid {n_phi}x{n_theta} needs {n_phi * n_theta}",
                             file=src, field="n_phi")
        table = cls(machine=meta.get("machine", ""), version=_parse(meta, "table_version", int, src),
                    phi_min_deg=_parse(meta, "phi_min_deg", float, src),
                    phi_max_deg=_parse(meta, "phi_max_deg", float, src),
                    theta_min_deg=_parse(meta, "theta_min_deg", float, src),
                    theta_max_deg=_parse(meta, "theta_max_deg", float, src),
                    m_min_deg=_parse(meta, "m_min_deg", float, src), m_max_deg=_parse(meta, "m_max_deg", float, src),
                    max_step_deg=_parse(meta, "max_step_deg", float, src),
                    values=np.zeros((n_phi, n_theta, 2)), reference=reference, source=src)
        phi, theta = table.phi_nodes_deg(), table.theta_nodes_deg()
        for r, row in enumerate(rows, start=1):
            if len(row) != 4:
                raise InputError(f"expected 4 fields, got {len(row)}", file=src, row=r)
            nums = []
            for name, text in zip(columns, row):
                try:
                    nums.append(float(text))
                except ValueError:
                    raise InputError(f"not a number: {text!r}", file=src, row=r, field=name) from None
            i, j = divmod(r - 1, n_theta)
            for name, got, want in (("phi_deg", nums[0], phi[i]), ("theta_deg", nums[1], theta[j])):
                if not abs(got - want) <= 1e-9 * max(1.0, abs(want)):
                    raise InputError(f"{got:g} is not the grid node {want:.10g} expected at this row "
                                     "(rows go phi-major, theta fastest)", file=src, row=r, field=name)
            table.values[i, j] = nums[2:]
        _check_sums(table, meta, src, fv)
        return table


# ---- helpers ------------------------------------------------------------------------------

def _nodes(lo: float, hi: float, n: int) -> np.ndarray:
    """n nodes from lo to hi, deg: lo + k*(hi-lo)/(n-1), the last one exactly hi."""
    k = np.arange(n, dtype=np.float64)
    out = lo + k * ((hi - lo) / (n - 1)) if n > 1 else np.array([float(lo)])
    if n > 1:
        out[-1] = hi
    return out


def _num(x) -> str:
    """Shortest text that reads back to the same double (repr), integers without '.0'."""
    x = float(x)
    if x.is_integer() and abs(x) < 1e15 and math.copysign(1.0, x) > 0:
        return str(int(x))
    return repr(x)


def _check_format_version(v, src: str) -> int:
    """The format version of a file; version 1 (absolute commands) is read as a table without reference."""
    if isinstance(v, bool) or v not in READ_VERSIONS:
        raise InputError(f"format_version {v!r} not supported (this reader knows "
                         f"{', '.join(map(str, READ_VERSIONS))})", file=src, field="format_version")
    return int(v)


def _reference(doc: dict, src: str) -> NominalReference | None:
    kind = doc.get("kind")
    if kind == "none":
        return None
    if kind != "nominal_ik":
        raise InputError(f"reference kind must be 'nominal_ik' or 'none', got {kind!r}", file=src,
                         field="reference")
    ref = NominalReference(**{k: _float(doc, k, src) for k in NominalReference.KEYS})
    if ref.defect():
        raise InputError(ref.defect(), file=src, field="reference")
    return ref


def lookup(values: np.ndarray, reference: NominalReference | None, phi_lim: tuple[float, float],
           theta_lim: tuple[float, float], phi_deg, theta_deg) -> tuple[np.ndarray, np.ndarray]:
    """FB_CompTableLookup: ``reference(phi, theta) + bilinear(values)`` (deg), and the inside mask.

    Shared by :meth:`CompTable.interpolate` and the PLC twin, so both give the same bits.
    """
    m, inside = bilinear(values, phi_lim, theta_lim, phi_deg, theta_deg)
    if reference is not None:
        m = reference.commands_deg(phi_deg, theta_deg) + m
        m[~inside] = np.nan
    return m, inside


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
        return kind(meta[key])
    except ValueError:
        raise InputError(f"bad value {meta[key]!r} in the # header lines", file=src, field=key) from None


def _check_sums(table: CompTable, doc: dict, src: str, format_version: int = FORMAT_VERSION) -> None:
    """Compare the checksums stored in a file with the data read from it; both must be present.

    Format 3 carries ``crc32`` (:meth:`CompTable.crc32`: header image and data); formats 1 and 2 carry
    ``crc16_ccitt`` (CRC-16/CCITT-FALSE over the data only), still read. A version-1 file's SHA-256 covers
    the values only (it has no reference).
    """
    name = "crc32" if format_version >= 3 else "crc16_ccitt"
    crc_text, sha_text = doc.get(name), doc.get("sha256")
    for key, text in ((name, crc_text), ("sha256", sha_text)):
        if text is None:
            raise InputError(f"no {key} checksum: a table must carry {name} and sha256 "
                             "(write it with pmcal; edited files are refused)", file=src, field=key)
    if not np.isfinite(table.values).all():
        return   # validate() names the bad node; a checksum message would hide it
    try:
        crc = int(str(crc_text), 16)
    except ValueError:
        raise InputError(f"bad CRC {crc_text!r}", file=src, field=name) from None
    want = table.crc32() if format_version >= 3 else binascii.crc_hqx(table.data_bytes(), 0xFFFF)
    if crc != want:
        width = 8 if format_version >= 3 else 4
        raise InputError(f"CRC mismatch: file says 0x{crc:0{width}X}, data give 0x{want:0{width}X} "
                         "(file edited or damaged)", file=src, field=name)
    sha = table.sha256() if format_version >= 2 else hashlib.sha256(table.data_bytes()).hexdigest()
    if str(sha_text).lower() != sha:
        raise InputError("SHA-256 mismatch between the file's checksum and its data (file edited or damaged)",
                         file=src, field="sha256")
