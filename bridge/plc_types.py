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

from pmcal.bridge.comptable import FORMAT_VERSION, NPHI_MAX, NTHETA_MAX, CompTable, GridLimits
from pmcal.bridge.nominal import REFERENCE_NOMINAL_IK, REFERENCE_NONE

#: FB_CompTableManager.tCommitTimeout default (s): a checked table that motion keeps from being swapped
#: in is dropped with SWAP_TIMEOUT after this long. The bridge's ack time-out (5 s) is longer, so the
#: user always sees the PLC's verdict.
COMMIT_TIMEOUT_S = 4.0
#: interface version of GVL_CompTable (bumped when any layout below changes)
INTERFACE_VERSION = 2
LREAL_SIZE = 8
#: ARRAY[0..NPHI_MAX-1, 0..NTHETA_MAX-1, 0..1] OF LREAL
SHADOW_LREALS = NPHI_MAX * NTHETA_MAX * 2
SHADOW_SIZE = SHADOW_LREALS * LREAL_SIZE
ROW_SIZE = NTHETA_MAX * 2 * LREAL_SIZE          # one phi row of the PLC array, bytes


class Status(IntEnum):
    """E_CompTableStatus: result of the last commit (PLC writes it before the acknowledgement)."""

    NONE = 0
    OK = 1
    BUSY = 2
    WITHDRAWN = 10             # the bridge cleared nCommitVersion before the swap
    FORMAT_VERSION = 101
    VERSION_MISMATCH = 102     # nCommitVersion <> header.nTableVersion
    STALE_VERSION = 103        # not newer than the active table
    GRID_SIZE = 104
    GRID_LIMITS = 105
    LIMITS = 106
    CRC_MISMATCH = 107
    NOT_FINITE = 108
    OUT_OF_RANGE = 109
    STEP_TOO_LARGE = 110
    CRC_SELFTEST = 111         # F_DATA_TO_CRC16_CCITT does not give 16#29B1 for '123456789'
    SWAP_TIMEOUT = 112         # motion did not allow the swap within tCommitTimeout
    REFERENCE_MISMATCH = 113   # header's nominal-IK reference is not the PLC's (nReference, nReferenceCrc)

    @property
    def is_rejection(self) -> bool:
        return self >= 100


class State(IntEnum):
    """E_CompTableState: step of FB_CompTableManager."""

    IDLE = 0
    CHECKING = 1
    WAIT_MOTION = 2


class LookupResult(IntEnum):
    """E_CompTableLookup: outcome of FB_CompTableLookup."""

    OK = 0
    OUT_OF_GRID = 1
    NO_TABLE = 2


#: ST_CompTableHeader: 7 LREAL, UDINT, 4 x UINT/WORD, STRING(31), nReference UINT, nReferenceCrc WORD
#: = 104 bytes
_HEADER = struct.Struct("<7dI4H32s2H")
#: ST_CompTableState: nAckVersion, nActiveVersion, nCycle (UDINT); eStatus, nActiveCrc, eState,
#: nReserved (UINT/WORD/INT); nStagingOwner (UDINT) = 24 bytes
_STATE = struct.Struct("<3I4HI")
#: FB_CompTableManager.tStagingLease default (s): an owner that stays silent this long loses the staging
STAGING_LEASE_S = 30.0
#: ST_CompTableLookupIn: fPhi, fTheta (LREAL), nSeq (UDINT), 4 reserved = 24 bytes
_LOOKUP_IN = struct.Struct("<2dI4x")
#: ST_CompTableLookupOut: fM1, fM2 (LREAL), nSeq, nTableVersion (UDINT), eResult (INT), 6 reserved
_LOOKUP_OUT = struct.Struct("<2d2IH6x")

HEADER_SIZE = _HEADER.size
STATE_SIZE = _STATE.size
LOOKUP_IN_SIZE = _LOOKUP_IN.size
LOOKUP_OUT_SIZE = _LOOKUP_OUT.size


@dataclass(kw_only=True)
class Header(GridLimits):
    """ST_CompTableHeader: what the PLC needs to check and use a table (deg). Limits first, as packed."""

    table_version: int
    format_version: int
    n_phi: int
    n_theta: int
    crc: int
    machine: str
    reference: int = REFERENCE_NONE      # nReference: 0 absolute commands, 1 corrections to the nominal IK
    reference_crc: int = 0               # nReferenceCrc: NominalReference.crc16() of the reference geometry

    def pack(self) -> bytes:
        name = self.machine.encode("ascii")[:31]
        return _HEADER.pack(*self.limits().values(), self.table_version, self.format_version, self.n_phi,
                            self.n_theta, self.crc, name, self.reference, self.reference_crc)

    @classmethod
    def unpack(cls, data: bytes) -> "Header":
        f = _HEADER.unpack(data)
        names = [x.name for x in dataclasses.fields(GridLimits)]
        return cls(**dict(zip(names, f[:7])), table_version=f[7], format_version=f[8],
                   n_phi=f[9], n_theta=f[10], crc=f[11], machine=f[12].split(b"\0", 1)[0].decode("ascii", "replace"),
                   reference=f[13], reference_crc=f[14])

    @classmethod
    def of(cls, table: CompTable) -> "Header":
        return cls(**table.limits(), table_version=int(table.version), format_version=FORMAT_VERSION,
                   n_phi=table.n_phi, n_theta=table.n_theta, crc=table.crc16(), machine=table.machine,
                   reference=REFERENCE_NONE if table.reference is None else REFERENCE_NOMINAL_IK,
                   reference_crc=0 if table.reference is None else table.reference.crc16())


@dataclass(frozen=True)
class PlcState:
    """ST_CompTableState: the handshake outputs of the PLC."""

    ack_version: int
    active_version: int
    cycle: int
    status: Status
    active_crc: int
    state: State
    staging_owner: int = 0       # session token of the client that owns the staging area (0: free)

    def pack(self) -> bytes:
        return _STATE.pack(self.ack_version, self.active_version, self.cycle, int(self.status),
                           self.active_crc, int(self.state), 0, self.staging_owner)

    @classmethod
    def unpack(cls, data: bytes) -> "PlcState":
        ack, active, cycle, status, crc, state, _, owner = _STATE.unpack(data)
        return cls(ack, active, cycle, _enum(Status, status), crc, _enum(State, state), owner)


@dataclass(frozen=True)
class LookupIn:
    """ST_CompTableLookupIn: a target orientation (deg) and a request sequence number."""

    phi_deg: float
    theta_deg: float
    seq: int

    def pack(self) -> bytes:
        return _LOOKUP_IN.pack(self.phi_deg, self.theta_deg, self.seq)

    @classmethod
    def unpack(cls, data: bytes) -> "LookupIn":
        return cls(*_LOOKUP_IN.unpack(data))


@dataclass(frozen=True)
class LookupOut:
    """ST_CompTableLookupOut: motor targets (deg) for request ``seq`` from table ``table_version``."""

    m1_deg: float
    m2_deg: float
    seq: int
    table_version: int
    result: LookupResult

    def pack(self) -> bytes:
        return _LOOKUP_OUT.pack(self.m1_deg, self.m2_deg, self.seq, self.table_version, int(self.result))

    @classmethod
    def unpack(cls, data: bytes) -> "LookupOut":
        m1, m2, seq, ver, res = _LOOKUP_OUT.unpack(data)
        return cls(m1, m2, seq, ver, _enum(LookupResult, res))


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
    Symbol("shadow", "aShadow", f"ARRAY [0..{NPHI_MAX - 1},0..{NTHETA_MAX - 1},0..1] OF LREAL",
           SHADOW_SIZE, "bridge"),
    Symbol("commit_version", "nCommitVersion", "UDINT", 4, "bridge"),
    Symbol("staging_claim", "nStagingClaim", "UDINT", 4, "bridge"),
    Symbol("state", "stState", "ST_CompTableState", STATE_SIZE, "plc"),
    Symbol("active_header", "stActiveHeader", "ST_CompTableHeader", HEADER_SIZE, "plc"),
    Symbol("lookup_in", "stLookupIn", "ST_CompTableLookupIn", LOOKUP_IN_SIZE, "bridge"),
    Symbol("lookup_out", "stLookupOut", "ST_CompTableLookupOut", LOOKUP_OUT_SIZE, "plc"),
)
SYMBOL = {s.key: s for s in SYMBOLS}
#: the allow-lists: what the bridge may write to push a table, and to ask for motor targets
PUSH_WRITES = frozenset({"shadow_header", "shadow", "commit_version", "staging_claim"})
LOOKUP_WRITES = frozenset({"lookup_in"})


def _enum(kind, value: int):
    """Decode an enum value; an unknown code (e.g. a corrupted reply) stays an int."""
    try:
        return kind(value)
    except ValueError:
        return value


def shadow_rows(table: CompTable) -> bytes:
    """The first ``n_phi`` rows of the PLC array ``aShadow`` holding ``table`` (unused theta slots 0).

    Row i starts at byte ``i * ROW_SIZE``; node (i, j), motor k at ``((i*NTHETA_MAX + j)*2 + k)*8``.
    """
    buf = np.zeros((table.n_phi, NTHETA_MAX, 2), dtype="<f8")
    buf[:, :table.n_theta, :] = table.values
    return buf.tobytes()


def used_values(header: Header, shadow: np.ndarray) -> np.ndarray:
    """The used nodes (n_phi, n_theta, 2) of a full shadow array (NPHI_MAX, NTHETA_MAX, 2)."""
    return shadow[:header.n_phi, :header.n_theta, :]
