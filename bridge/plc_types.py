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

from pmcal.bridge.comptable import HEADER_STRUCT, NPHI_MAX, NTHETA_MAX, CompTable, GridLimits, pack_header
from pmcal.bridge.nominal import REFERENCE_NONE

#: FB_CompTableManager.tCommitTimeout default (s): a checked table that motion keeps from being swapped
#: in is dropped with SWAP_TIMEOUT after this long. The bridge's ack time-out (5 s) is longer, so the
#: user always sees the PLC's verdict.
COMMIT_TIMEOUT_S = 4.0
#: interface version of GVL_CompTable (bumped when any layout below changes)
INTERFACE_VERSION = 3
LREAL_SIZE = 8
#: ARRAY[0..NPHI_MAX-1, 0..NTHETA_MAX-1, 0..1] OF LREAL
SHADOW_LREALS = NPHI_MAX * NTHETA_MAX * 2
SHADOW_SIZE = SHADOW_LREALS * LREAL_SIZE
ROW_SIZE = NTHETA_MAX * 2 * LREAL_SIZE          # one phi row of the PLC array, bytes


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
    MACHINE_MISMATCH = 114     # GVL_CompTableParam.MACHINE is set and the header names another machine

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


#: ST_CompTableHeader (bridge.comptable.HEADER_STRUCT: the CRC covers this image): 104 bytes
_HEADER = HEADER_STRUCT
#: ST_CompTableState: nAckToken, nActiveVersion, nCycle (UDINT); eStatus, eState (INT); nActiveCrc (DWORD);
#: nStagingOwner (UDINT) = 24 bytes
_STATE = struct.Struct("<3I2H2I")
#: GVL_CompTableParam.STAGING_LEASE (s): an owner silent this long while another client claims loses the
#: staging area; a client waits this long (plus a margin) for it
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
    crc: int                             # nCrc: CRC-32 over this header with nCrc = 0, then the used nodes
    machine: str
    reference: int = REFERENCE_NONE      # nReference: 0 absolute commands, 1 corrections to the nominal IK
    reference_crc: int = 0               # nReferenceCrc: NominalReference.crc32() of the reference geometry

    def pack(self) -> bytes:
        return pack_header(self.limits(), version=self.table_version, format_version=self.format_version,
                           n_phi=self.n_phi, n_theta=self.n_theta, reference=self.reference, crc=self.crc,
                           reference_crc=self.reference_crc, machine=self.machine)

    @classmethod
    def unpack(cls, data: bytes) -> "Header":
        f = _HEADER.unpack(data)
        names = [x.name for x in dataclasses.fields(GridLimits)]
        return cls(**dict(zip(names, f[:7])), table_version=f[7], format_version=f[8], n_phi=f[9], n_theta=f[10],
                   reference=f[11], crc=f[12], reference_crc=f[13],
                   machine=f[14].split(b"\0", 1)[0].decode("ascii", "replace"))

    @classmethod
    def of(cls, table: CompTable) -> "Header":
        return cls.unpack(table.header_bytes(table.crc32()))


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
    """The first ``n_phi`` rows of the PLC array ``aShadow`` holding ``table`` (unused theta slots 0).

    Row i starts at byte ``i * ROW_SIZE``; node (i, j), motor k at ``((i*NTHETA_MAX + j)*2 + k)*8``.
    """
    buf = np.zeros((table.n_phi, NTHETA_MAX, 2), dtype="<f8")
    buf[:, :table.n_theta, :] = table.values
    return buf.tobytes()


def used_values(header: Header, shadow: np.ndarray) -> np.ndarray:
    """The used nodes (n_phi, n_theta, 2) of a full shadow array (NPHI_MAX, NTHETA_MAX, 2)."""
    return shadow[:header.n_phi, :header.n_theta, :]
