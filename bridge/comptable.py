"""The compensation table: a grid over 1 to 3 task axes holding the commands of N motors (format 4).

Format specification: ``docs/compensation_table.md``. Units: each task axis and each motor carries its
unit (``deg`` for angles and revolute motors, ``mm`` for positions and prismatic motors); this module
never converts.

Axis ``a`` spans ``axes[a].min`` to ``axes[a].max`` in ``axes[a].n`` nodes, both ends included.
``values[i0, ..., k]`` (shape ``(n_0, ..., n_{A-1}, N)``) is, for motor ``k`` (m1..mN), what the table
holds at the node, by its ``reference`` (header ``nReference``):

- ``None`` (0): the absolute command that makes the calibrated machine reach the node;
- a :class:`~pmcal.bridge.nominal.NominalReference` (1): the correction added to the ocpm nominal
  closed-form IK that the PLC computes in ST (only 2 axes phi/theta and 2 revolute motors);
- :data:`CONTROLLER` (2, ``"controller"`` in the files): the correction the integrator adds to the motion
  controller's *own* nominal inverse kinematics, ``m_calibrated(node) - m_nominal(node)`` (as machine-tool
  volumetric compensation). The PLC's table code never sees that IK, so for such a table each motor's
  ``min``/``max`` bound the *correction* (and ``max_step`` its change between neighbours), not the
  command; the commands' own limits stay with the controller (its axis limits).
 The PLC stores the used values as one flat
``ARRAY[0..NVALUES_MAX-1] OF LREAL`` in C order of this array (last axis, then motor, fastest),
little-endian IEEE-754 double. Files (JSON, CSV; formats 1 to 3 still read): :mod:`pmcal.bridge.comptable_files`.

Typical use by the identification code::

    table = CompTable.from_grid(fill, machine="delta_3dof", version=7,
                                axes=[Axis("x", "mm", -100, 100, 11), Axis("y", "mm", -100, 100, 11)],
                                motors=[Motor("m1", "deg", -35, 80, 10)] * 3)   # names fixed to m1..mN
    table.validate()
    table.save("comp.json")          # JSON plus comp.csv beside it, both written atomically
"""

from __future__ import annotations

import hashlib
import math
import re
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, NamedTuple, Sequence

import numpy as np

from pmcal.bridge.nominal import REFERENCE_CONTROLLER, REFERENCE_NOMINAL_IK, REFERENCE_NONE, NominalReference
from pmcal.errors import InputError

FORMAT = "pmcal-comptable"
#: 4: 1-3 task axes, N motors with per-motor limits, flat PLC array; 3 (read): 2 axes, 2 motors, CRC-32;
#: 2 (read): CRC-16 over the data only; 1 (read, converted): absolute commands.
FORMAT_VERSION = 4
READ_VERSIONS = (1, 2, 3, 4)
#: fixed PLC sizes (GVL_CompTableParam): axes, motors and LREAL values a table holds at most
NAXES_MAX = 3
NMOTOR_MAX = 6
NVALUES_MAX = 20_000
#: table versions are UDINT on the PLC; 0 means "no table"
VERSION_MAX = 2**32 - 1
#: STRING(27) on the PLC
MACHINE_MAX_LEN = 27
#: largest azimuth span (deg) of a table with the nominal-IK reference (axis 0 is phi, never wrapped)
PHI_SPAN_MAX_DEG = 360.0
#: largest magnitude of a grid limit, motor limit or max step (deg or mm): GVL_CompTableParam.LIMIT_ABS_MAX,
#: so every difference the PLC forms between limits or commands stays finite
LIMIT_ABS_MAX = 1.0e6
LIMIT_ABS_MAX_DEG = LIMIT_ABS_MAX
#: GVL_CompTableParam.CORRECTION_ABS_MAX: largest correction bound (deg or mm, per motor) a table with the
#: controller reference may declare; the PLC refuses wider bounds (LIMITS) whatever the table says
CORRECTION_ABS_MAX = 5.0
#: ST_CompTableHeader, 248 bytes (pack_mode 1, naturally aligned): aAxisMin[3], aAxisMax[3], aMotorMin[6],
#: aMotorMax[6], aMaxStep[6] (LREAL), nTableVersion UDINT, nFormatVersion, nAxes, aN[3], nMotors,
#: nReference UINT, nPrismatic WORD, nCrc, nReferenceCrc DWORD, sMachine STRING(27)
HEADER_STRUCT = struct.Struct(f"<{2 * NAXES_MAX + 3 * NMOTOR_MAX}dI{NAXES_MAX + 5}H2I28s")
#: the axes and motors of the seeded machines' tables (formats 1 to 3 hold these only)
PHI, THETA = "phi", "theta"
MOTOR_UNITS = ("deg", "mm")
_NAME = re.compile(r"[A-Za-z][A-Za-z0-9]*")

Fill = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class ControllerReference:
    """Reference kind 2 (``nReference = 2``): the values are corrections to add to the motion controller's
    own nominal inverse kinematics. Nothing to carry (``nReferenceCrc = 0``): the PLC's table code never
    computes that IK; the integrator adds the looked-up correction to it (docs/commissioning.md)."""

    KIND = "controller"

    def as_dict(self) -> dict:
        return {"kind": self.KIND}

    def pack(self) -> bytes:
        """No geometry: nothing is appended to the data for the SHA-256."""
        return b""

    def crc32(self) -> int:
        """``nReferenceCrc``: 0."""
        return 0

    def defect(self) -> str | None:
        return None


#: the controller reference (kind 2); ``reference="controller"`` in :class:`CompTable` means this
CONTROLLER = ControllerReference()
Reference = NominalReference | ControllerReference


def crc32(data: bytes, crc: int = 0) -> int:
    """CRC-32 (IEEE 802.3, reflected polynomial 0xEDB88320, init and final XOR 0xFFFFFFFF) as the PLC's
    ``F_CompTableCrc32(pData, cbData, nCrc := 0)`` computes it; ``zlib.crc32``.

    Check value: ``crc32(b"123456789") == 0xCBF43926``. Chainable like the PLC function:
    ``crc32(b, crc32(a)) == crc32(a + b)``.
    """
    return zlib.crc32(data, crc)


@dataclass(frozen=True)
class Axis:
    """A task axis of the grid: ``name`` (letters and digits), ``unit`` (``deg``/``mm``), first and last
    node ``min``/``max`` in that unit, ``n`` nodes (both ends included)."""

    name: str
    unit: str
    min: float
    max: float
    n: int

    @property
    def column(self) -> str:
        """CSV column of the axis, e.g. ``x_mm``, ``phi_deg``."""
        return f"{self.name}_{self.unit}"

    def nodes(self) -> np.ndarray:
        """The node coordinates: ``min + k*(max-min)/(n-1)``, the last one exactly ``max``."""
        return _nodes(self.min, self.max, self.n)

    @classmethod
    def of_column(cls, column: str, lo: float, hi: float, n: int) -> "Axis":
        """An axis from a task-coordinate column name such as ``x_mm`` or ``phi_deg``."""
        name, _, unit = column.rpartition("_")
        return cls(name, unit, float(lo), float(hi), int(n))


@dataclass(frozen=True)
class Motor:
    """A motor of the table: ``name`` (m1..mN by position), ``unit`` (``deg`` revolute, ``mm`` prismatic),
    command limits ``min``/``max`` and the largest change ``max_step`` between neighbouring nodes."""

    name: str
    unit: str
    min: float
    max: float
    max_step: float

    @property
    def column(self) -> str:
        """CSV column of an absolute command, e.g. ``m1_deg``; a correction is ``d`` + this."""
        return f"{self.name}_{self.unit}"


class Defect(NamedTuple):
    """The first thing wrong with a table: what kind, a message, where (node index tuple and motor column)."""

    kind: str          # grid_size, grid_limits, limits, version, machine, not_finite, out_of_range, step, reference
    message: str
    node: tuple[int, ...] | None = None
    field: str | None = None


def multilinear(values: np.ndarray, lows: Sequence[float], highs: Sequence[float], points) -> tuple[np.ndarray,
                                                                                                  np.ndarray]:
    """Multilinear interpolation over 1 to 3 axes, with exactly the arithmetic of ``FB_CompTableLookup`` (ST).

    ``values`` has shape (n_0, ..., n_{A-1}, N); ``points`` (..., A) in the axes' units. Returns
    ``(m, inside)``: ``m`` of shape (..., N) and the mask of points inside the grid (outside: NaN).
    Per point and axis a, in IEEE double::

        u_a := (x_a - min_a) / (max_a - min_a) * (n_a - 1)
        i_a := MIN(TRUNC(u_a), n_a - 2);   f_a := u_a - i_a

    then the 2**A corner values (corner c: offset bit a of c along axis a) are reduced axis by axis, axis 0
    first: ``C[c] := C[2c] + (C[2c+1] - C[2c]) * f_a``. For two axes this is the bilinear scheme
    ``a := A[i,j] + (A[i+1,j] - A[i,j]) * fu; b := A[i,j+1] + ...; m := a + (b - a) * fv``.
    """
    n_axes = values.ndim - 1
    x = np.asarray(points, dtype=np.float64)
    if x.shape[-1] != n_axes:
        raise ValueError(f"points have {x.shape[-1]} coordinates, the table {n_axes} axes")
    lo, hi = np.asarray(lows, float), np.asarray(highs, float)
    inside = np.all((x >= lo) & (x <= hi), axis=-1)
    x = np.where(inside[..., None], x, lo)
    idx, frac = [], []
    for a in range(n_axes):
        n = values.shape[a]
        u = (x[..., a] - lo[a]) / (hi[a] - lo[a]) * float(n - 1)
        i = np.minimum(np.trunc(u), n - 2).astype(np.intp)
        idx.append(i)
        frac.append((u - i)[..., None])
    corners = [values[tuple(idx[a] + ((c >> a) & 1) for a in range(n_axes))] for c in range(2 ** n_axes)]
    for a in range(n_axes):
        corners = [corners[2 * c] + (corners[2 * c + 1] - corners[2 * c]) * frac[a]
                   for c in range(len(corners) // 2)]
    m = np.array(corners[0], dtype=np.float64)
    m[~inside] = np.nan
    return m, inside


def bilinear(values: np.ndarray, phi_lim: tuple[float, float], theta_lim: tuple[float, float],
             phi_deg, theta_deg) -> tuple[np.ndarray, np.ndarray]:
    """:func:`multilinear` of a 2-axis table at (phi, theta) (broadcast together)."""
    phi, theta = np.broadcast_arrays(np.asarray(phi_deg, float), np.asarray(theta_deg, float))
    return multilinear(values, (phi_lim[0], theta_lim[0]), (phi_lim[1], theta_lim[1]),
                       np.stack([phi, theta], axis=-1))


@dataclass(eq=False, init=False)
class CompTable:
    """A compensation table: ``values`` of shape (n_0, .., n_{A-1}, N) over ``axes`` for ``motors``.

    Keyword-only. ``version`` is the table version (UDINT, 1..2**32-1) that the PLC requires to increase
    strictly. ``reference``: what the values are corrections to: None (absolute commands), a
    :class:`NominalReference` (the PLC's ocpm nominal IK; only for axes phi, theta in deg and motors m1, m2
    in deg), or :data:`CONTROLLER` / ``"controller"`` (the motion controller's own nominal IK; any axes
    and motors; ``min``/``max``/``max_step`` of the motors then bound the correction). ``source`` (not part of the data) names the file
    the table was read from, for error messages. Without ``axes``/``motors`` the keywords of format 3
    (``phi_min_deg`` .. ``theta_max_deg``, ``m_min_deg``, ``m_max_deg``, ``max_step_deg``) build a
    2-axis table of 2 motors in deg.
    """

    machine: str
    version: int
    values: np.ndarray
    axes: tuple[Axis, ...]
    motors: tuple[Motor, ...]
    reference: Reference | None = None
    source: str | None = field(default=None, repr=False)

    def __init__(self, *, machine: str, version: int, values, axes: Sequence[Axis] | None = None,
                 motors: Sequence[Motor] | None = None, reference: Reference | str | None = None,
                 source: str | None = None, **legacy) -> None:
        if reference == ControllerReference.KIND:
            reference = CONTROLLER
        elif isinstance(reference, str):
            raise ValueError(f"reference must be 'controller', a NominalReference, CONTROLLER or None, "
                             f"got {reference!r}")
        self.machine, self.version, self.reference, self.source = machine, version, reference, source
        self.values = np.ascontiguousarray(values, dtype="<f8")
        if axes is None or motors is None:
            axes, motors = _legacy_axes(self.values, legacy, source)
        elif legacy:
            raise TypeError(f"unexpected keywords {sorted(legacy)} next to axes/motors")
        self.axes = tuple(Axis(a.name, a.unit, float(a.min), float(a.max), int(a.n)) for a in axes)
        self.motors = tuple(Motor(f"m{k + 1}", m.unit, float(m.min), float(m.max), float(m.max_step))
                            for k, m in enumerate(motors))
        want = tuple(a.n for a in self.axes) + (len(self.motors),)
        if self.values.shape != want:
            raise InputError(f"table values have shape {self.values.shape}, axes and motors say {want}",
                             file=source, field="values")

    # ---- geometry -------------------------------------------------------------------------
    @property
    def n_axes(self) -> int:
        return len(self.axes)

    @property
    def n_motors(self) -> int:
        return len(self.motors)

    @property
    def shape(self) -> tuple[int, ...]:
        """Nodes per axis."""
        return tuple(a.n for a in self.axes)

    def nodes(self) -> np.ndarray:
        """Node coordinates (n_0, .., n_{A-1}, A) in the axes' units, C order as ``values``."""
        grids = np.meshgrid(*(a.nodes() for a in self.axes), indexing="ij")
        return np.stack(grids, axis=-1)

    @property
    def reference_code(self) -> int:
        """``nReference`` of the header: 0 absolute, 1 ocpm nominal IK (PLC), 2 controller's own IK."""
        if self.reference is None:
            return REFERENCE_NONE
        return REFERENCE_CONTROLLER if isinstance(self.reference, ControllerReference) else REFERENCE_NOMINAL_IK

    @property
    def controller_reference(self) -> bool:
        """The values are corrections to the controller's own IK (kind 2): limits bound the corrections."""
        return isinstance(self.reference, ControllerReference)

    def columns(self) -> tuple[str, ...]:
        """CSV columns: the axes, then the motors (``dm1_deg`` .. for a table with a reference)."""
        d = "" if self.reference is None else "d"
        return tuple(a.column for a in self.axes) + tuple(d + m.column for m in self.motors)

    # the seeded machines' names for a 2-axis table of 2 motors (phi, theta; m1, m2)
    n_phi = property(lambda self: self.axes[0].n)
    n_theta = property(lambda self: self.axes[1].n)
    phi_min_deg = property(lambda self: self.axes[0].min)
    phi_max_deg = property(lambda self: self.axes[0].max)
    theta_min_deg = property(lambda self: self.axes[1].min)
    theta_max_deg = property(lambda self: self.axes[1].max)
    m_min_deg = property(lambda self: self.motors[0].min)
    m_max_deg = property(lambda self: self.motors[0].max)
    max_step_deg = property(lambda self: self.motors[0].max_step)

    def phi_nodes_deg(self) -> np.ndarray:
        return self.axes[0].nodes()

    def theta_nodes_deg(self) -> np.ndarray:
        return self.axes[1].nodes()

    def with_version(self, version: int) -> "CompTable":
        """A copy with another table version (values shared, read-only use)."""
        return CompTable(machine=self.machine, version=int(version), values=self.values, axes=self.axes,
                         motors=self.motors, reference=self.reference, source=self.source)

    # ---- checksums ------------------------------------------------------------------------
    def data_bytes(self) -> bytes:
        """The used values as the PLC stores them: little-endian doubles, C order (flat)."""
        return self.values.tobytes(order="C")

    def nominal_at_nodes(self) -> np.ndarray:
        """The reference commands at the nodes (same shape as ``values``); zeros without reference.

        Not available for the controller reference (the controller's IK is not part of the table):
        ValueError."""
        if self.reference is None:
            return np.zeros_like(self.values)
        if self.controller_reference:
            raise ValueError("a table of corrections to the controller's IK does not hold that IK: add the "
                             "controller's nominal commands to the values")
        x = self.nodes()
        return self.reference.commands_deg(x[..., 0], x[..., 1])

    def commands_at_nodes(self) -> np.ndarray:
        """Absolute motor commands at the nodes: reference + correction (ValueError for the controller
        reference, see :meth:`nominal_at_nodes`)."""
        return self.values if self.reference is None else self.nominal_at_nodes() + self.values

    def limited_at_nodes(self) -> np.ndarray:
        """What the motors' ``min``/``max``/``max_step`` apply to, at the nodes: the absolute commands,
        or for the controller reference the corrections themselves (the PLC's phases 4 to 6)."""
        return self.values if self.controller_reference else self.commands_at_nodes()

    def header_bytes(self, crc: int = 0) -> bytes:
        """The PLC header image of this table (ST_CompTableHeader) with ``nCrc = crc``."""
        ref = self.reference
        return pack_header(self.axes, self.motors, version=int(self.version), format_version=FORMAT_VERSION,
                           reference=self.reference_code, crc=crc,
                           reference_crc=0 if ref is None else ref.crc32(), machine=self.machine)

    def crc32(self) -> int:
        """CRC-32 (:func:`crc32`) over :meth:`header_bytes` with ``nCrc = 0``, then :meth:`data_bytes`:
        what the PLC recomputes over its copy before using the table."""
        return crc32(self.data_bytes(), crc32(self.header_bytes(0)))

    def sha256(self) -> str:
        """SHA-256 (hex) over :meth:`data_bytes` followed by the reference geometry's five LREALs
        (:meth:`NominalReference.pack`; nothing without a reference or with the controller reference, whose
        kind the CRC-32 seals through ``nReference``), for the files and the audit trail."""
        ref = b"" if self.reference is None else self.reference.pack()
        return hashlib.sha256(self.data_bytes() + ref).hexdigest()

    # ---- validation -----------------------------------------------------------------------
    def defect(self, active_version: int | None = None) -> Defect | None:
        """The first defect in the order the PLC checks (header, then data), or None.

        ``active_version``: the version active on the PLC; this table must be strictly newer.
        """
        return self.header_defect(active_version) or self.data_defect()

    def version_defect(self) -> Defect | None:
        """The version is not a UDINT 1..VERSION_MAX (the header image cannot hold it)."""
        if not (isinstance(self.version, (int, np.integer)) and 1 <= int(self.version) <= VERSION_MAX):
            return Defect("version", f"table version {self.version!r} outside 1..{VERSION_MAX}", field="table_version")
        return None

    def header_defect(self, active_version: int | None = None) -> Defect | None:
        """Grid size, reference, grid limits, motor limits and max steps, version, machine name."""
        size = self.size_defect()
        if size:
            return Defect("grid_size", size)
        if self.reference is not None and not self.controller_reference:
            if not self.reference_fits():
                return Defect("reference", "the nominal-IK reference needs axes phi, theta (deg) and motors "
                                           "m1, m2 (deg)")
            if self.reference.defect():
                return Defect("reference", self.reference.defect())
        for a in self.axes:
            if not (_bounded(a.min) and _bounded(a.max)):
                return Defect("grid_limits", f"axis {a.name}: limits must be finite, at most {LIMIT_ABS_MAX:g} "
                                             f"{a.unit} in size", field=a.column)
            if not a.min < a.max:
                return Defect("grid_limits", f"axis {a.name}: min must be below max", field=a.column)
        if self.reference_code == REFERENCE_NOMINAL_IK and self.axes[0].max - self.axes[0].min > PHI_SPAN_MAX_DEG:
            return Defect("grid_limits", f"phi span exceeds {PHI_SPAN_MAX_DEG:g} deg", field="phi_deg")
        for m in self.motors:
            if not (all(_bounded(x) for x in (m.min, m.max, m.max_step)) and m.min < m.max and m.max_step > 0.0):
                return Defect("limits", f"motor {m.name}: limits and max_step must be finite, at most "
                                        f"{LIMIT_ABS_MAX:g} {m.unit} in size, with min < max and max_step > 0",
                              field=m.column)
            if self.controller_reference and max(abs(m.min), abs(m.max)) > CORRECTION_ABS_MAX:
                return Defect("limits", f"motor {m.name}: correction bounds [{m.min:g}, {m.max:g}] {m.unit} exceed "
                                        f"the PLC's CORRECTION_ABS_MAX {CORRECTION_ABS_MAX:g}", field=m.column)
        bad_version = self.version_defect()
        if bad_version:
            return bad_version
        if active_version is not None and int(self.version) <= int(active_version):
            return Defect("stale_version", f"table version {self.version} is not newer than the active "
                                           f"version {active_version} on the PLC")
        if not (self.machine.isascii() and 0 < len(self.machine) <= MACHINE_MAX_LEN):
            return Defect("machine", f"machine name must be 1..{MACHINE_MAX_LEN} ASCII characters")
        return None

    def size_defect(self) -> str | None:
        """Why the grid does not fit the PLC (axes, nodes per axis, motors, total values), or None."""
        if not 1 <= self.n_axes <= NAXES_MAX:
            return f"{self.n_axes} axes: a table has 1..{NAXES_MAX}"
        if any(a.n < 2 for a in self.axes):
            return f"grid {'x'.join(map(str, self.shape))}: every axis needs at least 2 nodes"
        if not 1 <= self.n_motors <= NMOTOR_MAX:
            return f"{self.n_motors} motors: a table holds 1..{NMOTOR_MAX}"
        if self.values.size > NVALUES_MAX:
            return (f"grid {'x'.join(map(str, self.shape))} x {self.n_motors} motors = {self.values.size} values, "
                    f"more than the PLC's {NVALUES_MAX}")
        if any(m.unit not in MOTOR_UNITS for m in self.motors):
            return f"motor units must be one of {', '.join(MOTOR_UNITS)}"
        if any(not _NAME.fullmatch(a.name) or not _NAME.fullmatch(a.unit) for a in self.axes) \
                or len({a.name for a in self.axes}) < self.n_axes:
            return "axis names and units must be distinct words of letters and digits"
        return None

    def reference_fits(self) -> bool:
        """The nominal-IK reference applies: axes phi, theta in deg and two motors in deg."""
        return ([a.column for a in self.axes] == ["phi_deg", "theta_deg"]
                and [m.unit for m in self.motors] == ["deg", "deg"])

    def data_defect(self) -> Defect | None:
        """All values finite, then all within their motor's limits, then every step within its max_step.

        Limits and steps apply to the absolute commands (reference + correction) at the nodes; with the
        controller reference to the corrections (:meth:`limited_at_nodes`: the commands need the
        controller's IK, which the table does not hold; ``pmcal compensate`` checks them when it writes
        the table). Each check covers the whole table before the next starts (as FB_CompTableCheck's phases).
        """
        bad = ~np.isfinite(self.values)
        if bad.any():
            return self._node_defect("not_finite", bad, "is not a finite number")
        v = self.limited_at_nodes()
        bad = ~np.isfinite(v)
        if bad.any():
            return self._node_defect("not_finite", bad, "gives a nominal command out of reach")
        lo = np.array([m.min for m in self.motors])
        hi = np.array([m.max for m in self.motors])
        bad = (v < lo) | (v > hi)
        if bad.any():
            k = int(np.argwhere(bad)[0][-1])
            m = self.motors[k]
            what = "correction bounds" if self.controller_reference else "motor limits"
            return self._node_defect("out_of_range", bad, f"outside the {what} [{m.min:g}, {m.max:g}] "
                                                          f"{m.unit} of {m.name}")
        step_max = np.array([m.max_step for m in self.motors])
        for axis, a in enumerate(self.axes):
            step = np.abs(np.diff(v, axis=axis))
            bad = step > step_max
            if bad.any():
                *node, k = (int(x) for x in np.argwhere(bad)[0])
                nxt = list(node)
                nxt[axis] += 1
                m = self.motors[k]
                what = "correction step" if self.controller_reference else "step"
                return Defect("step", f"{what} of {step[tuple(node) + (k,)]:.6g} {m.unit} to the next node along "
                                      f"{a.name} {tuple(nxt)} exceeds max_step {m.max_step:g} {m.unit} of {m.name}",
                              tuple(node), self._field(k))
        return None

    def _field(self, k: int) -> str:
        """The CSV column of motor k's values (``dm1_deg`` for the controller reference)."""
        return ("d" if self.controller_reference else "") + self.motors[k].column

    def validate(self, active_version: int | None = None) -> "CompTable":
        """Raise :class:`InputError` naming file, row (CSV node row) and field on the first defect.

        Checks, in the PLC's order: grid size (1..3 axes of >= 2 nodes, 1..6 motors, at most 20 000
        values), reference, grid and motor limits (controller reference: correction bounds within
        :data:`CORRECTION_ABS_MAX`), version range (and newer than ``active_version`` when given), machine
        name, finiteness, motor ranges, steps between neighbours (controller reference: of the corrections;
        the commands are the controller's and not checked here). Returns ``self``.
        """
        d = self.defect(active_version)
        if d is None:
            return self
        if d.node is None:
            raise InputError(d.message, file=self.source, field=d.field)
        x = self.nodes()[d.node]
        where = "node " + str(d.node) + " at " + ", ".join(f"{a.name}={v:.6g} {a.unit}" for a, v in zip(self.axes, x))
        row = int(np.ravel_multi_index(d.node, self.shape)) + 1
        raise InputError(f"{where}: {d.message}", file=self.source, row=row, field=d.field)

    def _node_defect(self, kind: str, bad: np.ndarray, what: str) -> Defect:
        *node, k = (int(x) for x in np.argwhere(bad)[0])
        at = tuple(node) + (k,)
        col = self._field(k)
        if self.reference is None or self.controller_reference or kind == "not_finite":
            text = f"{col} = {float(self.values[at])!r} {what}"
        else:
            text = (f"command {self.motors[k].column} = nominal + correction {float(self.values[at])!r} = "
                    f"{float(self.commands_at_nodes()[at])!r} {what}")
        return Defect(kind, text, tuple(node), col)

    # ---- evaluation -----------------------------------------------------------------------
    def lookup(self, points) -> np.ndarray:
        """Motor commands (..., N) at task points (..., A), as FB_CompTableLookup on the PLC.

        ``reference + multilinear(values)`` (multilinear alone without reference), in that order of IEEE
        operations. With the controller reference: the interpolated corrections, which the caller adds to
        the controller's nominal IK at the same points. Raises :class:`InputError` if a point lies outside the grid (the PLC refuses it too).
        """
        m, inside = lookup(self.values, self.reference, [a.min for a in self.axes], [a.max for a in self.axes],
                           points)
        if not inside.all():
            box = ", ".join(f"{a.name} [{a.min:g}, {a.max:g}] {a.unit}" for a in self.axes)
            raise InputError(f"target outside the table grid {box}", file=self.source)
        return m

    def interpolate(self, phi_deg, theta_deg) -> np.ndarray:
        """:meth:`lookup` of a 2-axis (phi, theta) table: commands (..., N) deg."""
        phi, theta = np.broadcast_arrays(np.asarray(phi_deg, float), np.asarray(theta_deg, float))
        return self.lookup(np.stack([phi, theta], axis=-1))

    @classmethod
    def from_grid(cls, fill: Fill, *, machine: str, version: int, axes: Sequence[Axis], motors: Sequence[Motor],
                  reference: Reference | str | None = None, nominal: Fill | None = None) -> "CompTable":
        """Fill a table from ``fill(points[P, A]) -> commands[P, N]`` (absolute commands at the nodes, in
        C order: last axis fastest). Stored relative to ``reference`` (None: absolute). With the controller
        reference, ``nominal(points[P, A]) -> commands[P, N]`` is the controller's nominal IK and the table
        holds ``fill - nominal`` (``motors`` then bound those corrections). Not validated."""
        proto = cls(machine=machine, version=int(version), axes=axes, motors=motors,
                    values=np.zeros(tuple(a.n for a in axes) + (len(motors),)))
        x = proto.nodes()
        pts = x.reshape(-1, len(axes))
        m = np.asarray(fill(pts), dtype=np.float64)
        if m.shape != (pts.shape[0], len(motors)):
            raise ValueError(f"fill returned shape {m.shape}, expected ({pts.shape[0]}, {len(motors)})")
        m = m.reshape(proto.values.shape)
        if reference == ControllerReference.KIND or isinstance(reference, ControllerReference):
            if nominal is None:
                raise ValueError("the controller reference needs nominal= (the controller's nominal IK)")
            m = m - np.asarray(nominal(pts), dtype=np.float64).reshape(m.shape)
        elif reference is not None:
            m = m - reference.commands_deg(x[..., 0], x[..., 1])
        return cls(machine=machine, version=int(version), axes=proto.axes, motors=proto.motors, values=m,
                   reference=reference)

    @classmethod
    def from_setpoints(cls, setpoints: Callable[[np.ndarray, np.ndarray], np.ndarray], *, machine: str,
                       version: int, n_phi: int = 73, n_theta: int = 31,
                       phi_range_deg: tuple[float, float] = (0.0, 360.0),
                       theta_range_deg: tuple[float, float] = (0.0, 60.0),
                       motor_limits_deg: tuple[float, float] = (-180.0, 180.0), max_step_deg: float = 10.0,
                       reference: NominalReference | str | None = "nominal_ik") -> "CompTable":
        """A 2-axis (phi, theta) table of 2 motors from ``setpoints(phi_deg[P], theta_deg[P]) -> m_deg[P, 2]``
        (the seeded machines' tables). ``reference``: ``"nominal_ik"`` (default, :meth:`NominalReference.default`),
        a :class:`NominalReference`, or None (absolute commands). Not validated."""
        if isinstance(reference, str):
            if reference != "nominal_ik":
                raise ValueError(f"reference must be 'nominal_ik', a NominalReference or None, got {reference!r}")
            reference = NominalReference.default()
        axes = (Axis(PHI, "deg", *phi_range_deg, n_phi), Axis(THETA, "deg", *theta_range_deg, n_theta))
        motors = [Motor("m", "deg", motor_limits_deg[0], motor_limits_deg[1], max_step_deg)] * 2
        return cls.from_grid(lambda p: setpoints(p[:, 0], p[:, 1]), machine=machine, version=version, axes=axes,
                             motors=motors, reference=reference)

    # ---- files (pmcal.bridge.comptable_files) ----------------------------------------------
    def header_dict(self) -> dict:
        from pmcal.bridge.comptable_files import header_dict
        return header_dict(self)

    def to_json(self, path: str | Path) -> None:
        from pmcal.bridge.comptable_files import write_json
        write_json(self, path)

    def to_csv(self, path: str | Path) -> None:
        from pmcal.bridge.comptable_files import write_csv
        write_csv(self, path)

    def save(self, json_path: str | Path) -> tuple[Path, Path]:
        """Write ``json_path`` and the CSV beside it (same stem, ``.csv``); returns both paths.

        Both are checked first (:func:`pmcal.fileio.check_output`): the CSV beside replaces only a table
        CSV, never another file of that name (a campaign ``t.csv`` beside ``t.json``)."""
        from pmcal.bridge.comptable_files import SIDE_FILE_START
        from pmcal.fileio import check_output
        jp = Path(json_path)
        cp = jp.with_suffix(".csv")
        check_output(jp, suffixes=(".json",))
        check_output(cp, own=SIDE_FILE_START)
        self.to_json(jp)
        self.to_csv(cp)
        return jp, cp

    @classmethod
    def load(cls, path: str | Path) -> "CompTable":
        """Read a table from ``.json`` or ``.csv`` (by suffix), formats 1 to 4."""
        from pmcal.bridge.comptable_files import read_csv, read_json
        return read_csv(path) if Path(path).suffix.lower() == ".csv" else read_json(path)

    @classmethod
    def from_json(cls, path: str | Path) -> "CompTable":
        from pmcal.bridge.comptable_files import read_json
        return read_json(path)

    @classmethod
    def from_csv(cls, path: str | Path) -> "CompTable":
        from pmcal.bridge.comptable_files import read_csv
        return read_csv(path)


# ---- helpers ------------------------------------------------------------------------------

def pack_header(axes: Sequence[Axis], motors: Sequence[Motor], *, version: int, format_version: int,
                reference: int, crc: int, reference_crc: int, machine: str) -> bytes:
    """The ST_CompTableHeader image (:data:`HEADER_STRUCT`); unused axis and motor slots are 0."""
    pad_a = [0.0] * (NAXES_MAX - len(axes))
    pad_m = [0.0] * (NMOTOR_MAX - len(motors))
    prismatic = sum(1 << k for k, m in enumerate(motors) if m.unit == "mm")
    name = machine.encode("ascii", "replace")[:MACHINE_MAX_LEN]
    return HEADER_STRUCT.pack(*[a.min for a in axes], *pad_a, *[a.max for a in axes], *pad_a,
                              *[m.min for m in motors], *pad_m, *[m.max for m in motors], *pad_m,
                              *[m.max_step for m in motors], *pad_m, version, format_version, len(axes),
                              *[a.n for a in axes], *[0] * (NAXES_MAX - len(axes)), len(motors), reference,
                              prismatic, crc, reference_crc, name)


def lookup(values: np.ndarray, reference: Reference | None, lows: Sequence[float],
           highs: Sequence[float], points) -> tuple[np.ndarray, np.ndarray]:
    """FB_CompTableLookup: ``reference(x0, x1) + multilinear(values)``, and the inside mask (the controller
    reference: ``multilinear(values)``, the correction, as without reference).

    Shared by :meth:`CompTable.lookup` and the tests' PLC twin, so both give the same bits.
    """
    m, inside = multilinear(values, lows, highs, points)
    if isinstance(reference, NominalReference):
        x = np.asarray(points, float)
        m = reference.commands_deg(x[..., 0], x[..., 1]) + m
        m[~inside] = np.nan
    return m, inside


def _nodes(lo: float, hi: float, n: int) -> np.ndarray:
    """n nodes from lo to hi: lo + k*(hi-lo)/(n-1), the last one exactly hi."""
    k = np.arange(n, dtype=np.float64)
    out = lo + k * ((hi - lo) / (n - 1)) if n > 1 else np.array([float(lo)] * n)
    if n > 1:
        out[-1] = hi
    return out


def _bounded(x: float) -> bool:
    return math.isfinite(x) and abs(x) <= LIMIT_ABS_MAX


def _legacy_axes(values: np.ndarray, kw: dict, source: str | None) -> tuple[tuple[Axis, ...], tuple[Motor, ...]]:
    """Axes phi, theta and motors m1, m2 (deg) from format-3 keywords."""
    keys = ("phi_min_deg", "phi_max_deg", "theta_min_deg", "theta_max_deg", "m_min_deg", "m_max_deg",
            "max_step_deg")
    if set(kw) != set(keys):
        raise TypeError(f"CompTable needs axes= and motors=, or the keywords {', '.join(keys)}")
    if values.ndim != 3 or values.shape[2] != 2:
        raise InputError(f"table values must have shape (n_phi, n_theta, 2), got {values.shape}", file=source,
                         field="values")
    axes = (Axis(PHI, "deg", kw["phi_min_deg"], kw["phi_max_deg"], values.shape[0]),
            Axis(THETA, "deg", kw["theta_min_deg"], kw["theta_max_deg"], values.shape[1]))
    m = Motor("m", "deg", kw["m_min_deg"], kw["m_max_deg"], kw["max_step_deg"])
    return axes, (m, m)
