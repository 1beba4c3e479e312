"""The PLC's data types for the compensation table, byte for byte as declared in ``plc/*.TcDUT``.

Both transports move these exact byte images (ADS writes them as symbols, Modbus as the words of the
TwinCAT memory area), so the layouts live here once. All structs are ``{attribute 'pack_mode' := '1'}``
and naturally aligned, so their layout is the same with TwinCAT's default packing. Little-endian.
Units: degrees for every angle.
"""

from __future__ import annotations

import dataclasses
import struct
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from pmcal.bridge.comptable import (HEADER_STRUCT, NAXES_MAX, NMOTOR_MAX, NVALUES_MAX, Axis, CompTable, Motor,
                                    pack_header)
from pmcal.bridge.nominal import REFERENCE_CONTROLLER, REFERENCE_NONE  # noqa: F401  (REFERENCE_CONTROLLER: re-exported)

#: FB_CompTableManager.tCommitTimeout default (s): a checked table that motion keeps from being swapped
#: in is dropped with SWAP_TIMEOUT after this long. The bridge's ack time-out (5 s) is longer, so the
#: user always sees the PLC's verdict.
COMMIT_TIMEOUT_S = 4.0
#: a PLC's host name or IPv4 address in a target (ADS NETID@HOST[:PORT], Modbus HOST[:PORT])
HOST_PATTERN = r"[A-Za-z0-9_.\-]+"
#: interface version of GVL_CompTable (bumped when any layout below changes)
INTERFACE_VERSION = 5
LREAL_SIZE = 8
#: ARRAY[0..NVALUES_MAX-1] OF LREAL: the used values first, in C order (last axis, then motor, fastest)
SHADOW_LREALS = NVALUES_MAX
SHADOW_SIZE = SHADOW_LREALS * LREAL_SIZE


class Status(IntEnum):
    """E_CompTableStatus: result of the last commit (PLC writes it before the acknowledgement)."""

    NONE = 0
    OK = 1                     # swapped and saved (WritePersistentData done)
    BUSY = 2
    PLC_STARTING = 3           # the PLC re-checks its persistent table after a restart: commit again later
    OK_NOT_PERSISTED = 4       # swapped, but saving failed: a power cut without UPS restores the previous table
    WITHDRAWN = 10             # the owner cleared nCommitToken, or its lease ended, before the swap
    FORMAT_VERSION = 101
    VERSION_MISMATCH = 102     # header nTableVersion = 0
    STALE_VERSION = 103        # not newer than every table activated so far
    GRID_SIZE = 104
    GRID_LIMITS = 105
    LIMITS = 106
    CRC_MISMATCH = 107
    NOT_FINITE = 108
    OUT_OF_RANGE = 109
    STEP_TOO_LARGE = 110
    CRC_SELFTEST = 111         # F_CompTableCrc32 does not give 16#CBF43926 for '123456789'
    SWAP_TIMEOUT = 112         # motion did not allow the swap within tCommitTimeout
    REFERENCE_MISMATCH = 113   # header's nominal-IK reference is not the PLC's (nReference, nReferenceCrc)
    MACHINE_MISMATCH = 114     # the header names another machine than GVL_CompTableParam.MACHINE
    KIND_MISMATCH = 115        # correction table (nReference 2) to a command PLC (CORRECTIONS FALSE) or back
    MOTORS_MISMATCH = 116      # nMotors differs from GVL_CompTableParam.NMOTORS
    NOT_CONFIGURED = 117       # GVL_CompTableParam.MACHINE empty or NMOTORS 0: the PLC serves no table

    @property
    def is_rejection(self) -> bool:
        return self >= 100

    @property
    def activated(self) -> bool:
        """The committed table became active (saved or not)."""
        return self in (Status.OK, Status.OK_NOT_PERSISTED)


class State(IntEnum):
    """E_CompTableState: step of FB_CompTableManager."""

    IDLE = 0
    CHECKING = 1
    WAIT_MOTION = 2
    STARTING = 3               # after a restart, until the persistent table is re-checked
    PERSISTING = 4             # swapped; WritePersistentData runs, the acknowledgement follows


class LookupResult(IntEnum):
    """E_CompTableLookup: outcome of FB_CompTableLookup."""

    OK = 0
    OUT_OF_GRID = 1
    NO_TABLE = 2


#: ST_CompTableHeader (bridge.comptable.HEADER_STRUCT: the CRC covers this image): 248 bytes
_HEADER = HEADER_STRUCT
#: ST_CompTableState: nAckToken, nActiveVersion, nCycle (UDINT); eStatus, eState (INT); nActiveCrc (DWORD);
#: nStagingOwner (UDINT) = 24 bytes
_STATE = struct.Struct("<3I2H2I")
#: a client's token (FB_CompTableManager, interface 5): a random UDINT with this bit set, never 16#FFFFFFFF;
#: its complement (:func:`done_value`, bit clear) releases the staging area / withdraws the commit
TOKEN_BIT = 0x8000_0000


def new_token() -> int:
    """A fresh random client token: bit 31 set, not 16#FFFFFFFF (whose complement would be 0)."""
    import secrets

    while True:
        token = secrets.randbits(32) | TOKEN_BIT
        if token != 0xFFFF_FFFF:
            return token


def is_token(value: int) -> bool:
    """``value`` is a client token (a claim or a commit), not 0 nor a complement (a release or withdrawal)."""
    return bool(value & TOKEN_BIT) and value != 0xFFFF_FFFF


def done_value(token: int) -> int:
    """``NOT token``: written to nStagingClaim it releases the staging area, to nCommitToken it withdraws
    the owner's commit or clears its acknowledgement; only the current owner's complement counts."""
    return token ^ 0xFFFF_FFFF


#: GVL_CompTableParam.STAGING_LEASE (s): an owner silent this long while another client claims loses the
#: staging area; a client waits this long (plus a margin) for it
STAGING_LEASE_S = 30.0
#: ST_CompTableLookupIn: aX[3] (LREAL), nSeq (UDINT), 4 reserved = 32 bytes
_LOOKUP_IN = struct.Struct(f"<{NAXES_MAX}dI4x")
#: ST_CompTableLookupOut: aM[6] (LREAL), nSeq, nTableVersion (UDINT), eResult (INT), nMotors (UINT),
#: bCorrection (BOOL), 3 reserved = 64 bytes
_LOOKUP_OUT = struct.Struct(f"<{NMOTOR_MAX}d2IhH?3x")

HEADER_SIZE = _HEADER.size
STATE_SIZE = _STATE.size
LOOKUP_IN_SIZE = _LOOKUP_IN.size
LOOKUP_OUT_SIZE = _LOOKUP_OUT.size


@dataclass(kw_only=True)
class Header:
    """ST_CompTableHeader: what the PLC needs to check and use a table. Tuples hold the used axes and
    motors (``n``, ``axis_min``, ``axis_max`` one per axis; ``motor_min``, ``motor_max``, ``max_step``,
    ``prismatic`` one per motor); :meth:`pack` pads the unused slots with 0. ``n_axes``/``n_motors``
    (nAxes/nMotors) default to the tuples' lengths and may differ from them in a hostile header."""

    axis_min: tuple[float, ...]
    axis_max: tuple[float, ...]
    n: tuple[int, ...]
    motor_min: tuple[float, ...]
    motor_max: tuple[float, ...]
    max_step: tuple[float, ...]
    table_version: int
    format_version: int
    crc: int                             # nCrc: CRC-32 over this header with nCrc = 0, then the used values
    machine: str
    reference: int = REFERENCE_NONE      # nReference: 0 absolute commands, 1 corrections to the nominal IK,
    #                                      2 corrections to the controller's own IK
    reference_crc: int = 0               # nReferenceCrc: NominalReference.crc32() of the reference geometry
    prismatic: int = 0                   # nPrismatic: bit k set = motor k in mm
    n_axes: int | None = None
    n_motors: int | None = None

    def __post_init__(self) -> None:
        if self.n_axes is None:
            self.n_axes = len(self.n)
        if self.n_motors is None:
            self.n_motors = len(self.motor_min)

    def pack(self) -> bytes:
        axes = [Axis("a", "u", lo, hi, n) for lo, hi, n in zip(self.axis_min, self.axis_max, self.n)]
        motors = [Motor("m", "deg", lo, hi, st) for lo, hi, st in zip(self.motor_min, self.motor_max, self.max_step)]
        raw = bytearray(pack_header(axes[:NAXES_MAX], motors[:NMOTOR_MAX], version=self.table_version,
                                    format_version=self.format_version, reference=self.reference, crc=self.crc,
                                    reference_crc=self.reference_crc, machine=self.machine))
        struct.pack_into("<H", raw, _OFF_NAXES, self.n_axes & 0xFFFF)
        struct.pack_into("<HHH", raw, _OFF_NMOTORS, self.n_motors & 0xFFFF, self.reference, self.prismatic)
        return bytes(raw)

    @classmethod
    def unpack(cls, data: bytes) -> "Header":
        f = _HEADER.unpack(data)
        na, nm = NAXES_MAX, NMOTOR_MAX
        d = 2 * na + 3 * nm
        n_axes, n_motors = f[d + 2], f[d + 3 + na]
        ua, um = min(n_axes, na), min(n_motors, nm)
        return cls(axis_min=f[0:ua], axis_max=f[na:na + ua], motor_min=f[2 * na:2 * na + um],
                   motor_max=f[2 * na + nm:2 * na + nm + um], max_step=f[2 * na + 2 * nm:2 * na + 2 * nm + um],
                   table_version=f[d], format_version=f[d + 1], n=f[d + 3:d + 3 + ua], n_axes=n_axes,
                   n_motors=n_motors, reference=f[d + 4 + na], prismatic=f[d + 5 + na], crc=f[d + 6 + na],
                   reference_crc=f[d + 7 + na], machine=f[d + 8 + na].split(b"\0", 1)[0].decode("ascii", "replace"))

    @classmethod
    def of(cls, table: CompTable) -> "Header":
        return cls.unpack(table.header_bytes(table.crc32()))

    @property
    def n_values(self) -> int:
        """Values the header's grid uses (0 if it does not fit: F_CompTableValueCount)."""
        if not (1 <= self.n_axes <= NAXES_MAX and 1 <= self.n_motors <= NMOTOR_MAX) or min(self.n) < 2:
            return 0
        total = self.n_motors * int(np.prod(self.n))
        return total if total <= NVALUES_MAX else 0


#: byte offsets of nAxes and nMotors in ST_CompTableHeader
_OFF_NAXES = 8 * (2 * NAXES_MAX + 3 * NMOTOR_MAX) + 6
_OFF_NMOTORS = _OFF_NAXES + 2 + 2 * NAXES_MAX


@dataclass(frozen=True)
class PlcState:
    """ST_CompTableState: the handshake outputs of the PLC."""

    ack_token: int               # token of the commit answered (0 after nCommitToken := 0)
    active_version: int
    cycle: int
    status: Status
    state: State
    active_crc: int              # CRC-32 of the active table (its header's nCrc)
    staging_owner: int = 0       # token of the client that owns the staging area (0: free)

    def pack(self) -> bytes:
        return _STATE.pack(self.ack_token, self.active_version, self.cycle, int(self.status), int(self.state),
                           self.active_crc, self.staging_owner)

    @classmethod
    def unpack(cls, data: bytes) -> "PlcState":
        ack, active, cycle, status, state, crc, owner = _STATE.unpack(data)
        return cls(ack, active, cycle, _enum(Status, status), _enum(State, state), crc, owner)


@dataclass(frozen=True)
class LookupIn:
    """ST_CompTableLookupIn: a task point (the table's axis units, up to 3 coordinates) and a request
    sequence number."""

    x: tuple[float, ...]
    seq: int

    def pack(self) -> bytes:
        x = tuple(float(v) for v in self.x) + (0.0,) * (NAXES_MAX - len(self.x))
        return _LOOKUP_IN.pack(*x, self.seq)

    @classmethod
    def unpack(cls, data: bytes) -> "LookupIn":
        *x, seq = _LOOKUP_IN.unpack(data)
        return cls(tuple(x), seq)


@dataclass(frozen=True)
class LookupOut:
    """ST_CompTableLookupOut: motor targets (deg or mm; ``m`` holds ``n_motors`` values) for request ``seq``
    from table ``table_version``. ``correction`` (bCorrection): ``m`` are corrections to add to the
    controller's own nominal IK (a table with nReference = 2), not commands."""

    m: tuple[float, ...]
    seq: int
    table_version: int
    result: LookupResult
    n_motors: int = 0
    correction: bool = False

    def pack(self) -> bytes:
        m = tuple(self.m) + (0.0,) * (NMOTOR_MAX - len(self.m))
        return _LOOKUP_OUT.pack(*m, self.seq, self.table_version, int(self.result), self.n_motors,
                                bool(self.correction))

    @classmethod
    def unpack(cls, data: bytes) -> "LookupOut":
        f = _LOOKUP_OUT.unpack(data)
        nm = f[NMOTOR_MAX + 3]
        return cls(tuple(f[:min(nm, NMOTOR_MAX)]), f[NMOTOR_MAX], f[NMOTOR_MAX + 1],
                   _enum(LookupResult, f[NMOTOR_MAX + 2]), nm, bool(f[NMOTOR_MAX + 4]))

    @property
    def m1_deg(self) -> float:
        return self.m[0] if self.m else 0.0

    @property
    def m2_deg(self) -> float:
        return self.m[1] if len(self.m) > 1 else 0.0


@dataclass(frozen=True)
class Symbol:
    """A variable of GVL_CompTable: logical key, ST name and type, size in bytes, who writes it."""

    key: str
    st_name: str
    st_type: str
    size: int
    written_by: str            # "bridge" or "plc"


#: GVL_CompTable, in declaration order (plc/GVL_CompTable.TcGVL)
SYMBOLS: tuple[Symbol, ...] = (
    Symbol("interface_version", "nInterfaceVersion", "UINT", 2, "plc"),
    Symbol("shadow_header", "stShadowHeader", "ST_CompTableHeader", HEADER_SIZE, "bridge"),
    Symbol("shadow", "aShadow", f"ARRAY [0..{NVALUES_MAX - 1}] OF LREAL", SHADOW_SIZE, "bridge"),
    Symbol("commit", "nCommitToken", "UDINT", 4, "bridge"),
    Symbol("staging_claim", "nStagingClaim", "UDINT", 4, "bridge"),
    Symbol("state", "stState", "ST_CompTableState", STATE_SIZE, "plc"),
    Symbol("active_header", "stActiveHeader", "ST_CompTableHeader", HEADER_SIZE, "plc"),
    Symbol("lookup_in", "stLookupIn", "ST_CompTableLookupIn", LOOKUP_IN_SIZE, "bridge"),
    Symbol("lookup_out", "stLookupOut", "ST_CompTableLookupOut", LOOKUP_OUT_SIZE, "plc"),
)
SYMBOL = {s.key: s for s in SYMBOLS}
#: the allow-lists: what the bridge may write to push a table, and to ask for motor targets
PUSH_WRITES = frozenset({"shadow_header", "shadow", "commit", "staging_claim"})
LOOKUP_WRITES = frozenset({"lookup_in"})


def _enum(kind, value: int):
    """Decode an enum value; an unknown code (e.g. a corrupted reply) stays an int."""
    try:
        return kind(value)
    except ValueError:
        return value


def shadow_rows(table: CompTable) -> bytes:
    """The used part of the PLC array ``aShadow`` holding ``table``: its values, flat, C order.

    Value p (motor k of node (i0, .., i_{A-1})) at byte ``8*p``, ``p = ((i0*n1 + i1)*n2 + i2)*N + k``.
    """
    return table.data_bytes()


def used_values(header: Header, shadow: np.ndarray) -> np.ndarray:
    """The used values of a flat shadow array, shaped (n_0, .., n_{A-1}, N)."""
    return shadow[:header.n_values].reshape(tuple(header.n) + (header.n_motors,))
