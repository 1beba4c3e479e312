"""Modbus TCP protocol details in one place: the holding-register map of the compensation-table area.

TwinCAT's TF6250 server maps holding registers 0x3000..0x5FFF (12 288 registers) to the PLC memory
area %M (ADS index group 0x4020) from %MB0: register ``0x3000 + k`` is the WORD at ``%MB(2k)``,
stored little-endian. The PLC declares ``stMbArea AT %MB0 : ST_CompTableModbusArea`` (plc/), so the
registers below are that struct's words, and any PLC variable crosses Modbus as its memory image:
register k of a value = bytes ``2k, 2k+1`` of its little-endian image. For an LREAL this is what
pymodbus calls ``convert_to_registers([x], DATATYPE.FLOAT64, word_order="little")``.

A table of 20 000 LREALs (100x100 nodes x 2 motors) is 80 000 registers, more than the area (and than Modbus' 65 536 addresses),
so the table moves through a paged window: the bridge fills the window (FC16, at most 123 registers a
request; 120 used = 30 LREAL) of 2970 LREALs, then writes the page control block (index, count, command, sequence);
the PLC copies window <-> ``aShadow`` at ``index * window_lreals`` and echoes the sequence number.
Offsets are registers relative to ``base``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pmcal.bridge.plc_types import HEADER_SIZE, LOOKUP_IN_SIZE, LOOKUP_OUT_SIZE, STATE_SIZE

MAGIC = 0x504D                 # "PM"
PAGE_STORE = 1                 # window -> aShadow
PAGE_LOAD = 2                  # aShadow -> window
PAGE_OK = 0
PAGE_BAD = 1                   # index/count outside aShadow or unknown command

#: FC16 carries at most 123 registers, FC3 at most 125 (Modbus application protocol spec)
FC16_MAX = 123
FC3_MAX = 125

_REGS = {"shadow_header": HEADER_SIZE // 2, "state": STATE_SIZE // 2, "active_header": HEADER_SIZE // 2,
         "lookup_in": LOOKUP_IN_SIZE // 2, "lookup_out": LOOKUP_OUT_SIZE // 2, "commit": 2,
         "staging_claim": 2}
_OFFSET = {"shadow_header": "SHADOW_HEADER", "commit": "COMMIT_VERSION", "state": "STATE",
           "active_header": "ACTIVE_HEADER", "lookup_in": "LOOKUP_IN", "lookup_out": "LOOKUP_OUT",
           "staging_claim": "STAGING_CLAIM"}


@dataclass(frozen=True)
class ModbusMap:
    """Register map of ST_CompTableModbusArea (offsets in registers from ``base``)."""

    base: int = 0x3000             # first holding register of the area (TF6250 default: %MB0)
    area_size: int = 12288         # registers mapped (TF6250 default 0x3000..0x5FFF)
    window_lreals: int = 2970      # page window capacity, LREAL
    device_id: int = 1
    chunk: int = 120               # registers per FC16 request (whole LREALs, <= 123)
    read_chunk: int = FC3_MAX      # registers per FC3 request

    # ---- information block (PLC writes) ----
    MAGIC: int = 0
    INTERFACE_VERSION: int = 1      # register offset (the value is plc_types.INTERFACE_VERSION)
    VALUES_MAX: int = 2             # NVALUES_MAX
    MOTORS_MAX: int = 3             # NMOTOR_MAX
    WINDOW_LREALS: int = 4
    AXES_MAX: int = 5               # NAXES_MAX
    # ---- staging and commit (bridge writes) ----
    SHADOW_HEADER: int = 8         # ST_CompTableHeader, 124 registers
    COMMIT_VERSION: int = 132      # nCommitToken: UDINT, low word first
    PAGE_CONTROL: int = 134        # nPageIndex, nPageCount (LREAL), nPageCmd, nPageSeq
    # ---- PLC answers ----
    PAGE_ACK: int = 138            # nPageSeqDone, ePageStatus
    STATE: int = 140               # ST_CompTableState, 12 registers
    ACTIVE_HEADER: int = 152       # ST_CompTableHeader, 124 registers
    # ---- motor-target lookup ----
    LOOKUP_IN: int = 276           # ST_CompTableLookupIn, 16 registers (bridge writes)
    LOOKUP_OUT: int = 292          # ST_CompTableLookupOut, 32 registers (PLC writes)
    STAGING_CLAIM: int = 324       # UDINT session token, low word first (bridge writes; 0 releases)
    WINDOW: int = 384              # ARRAY[0..window_lreals-1] OF LREAL

    def __post_init__(self) -> None:
        if not 0 < self.chunk <= FC16_MAX or self.chunk % 4:
            raise ValueError(f"chunk must be a multiple of 4 registers, at most {FC16_MAX}")
        if not 0 < self.read_chunk <= FC3_MAX:
            raise ValueError(f"read_chunk must be at most {FC3_MAX}")
        if self.WINDOW + 4 * self.window_lreals > self.area_size or self.base + self.area_size > 65536:
            raise ValueError("window does not fit the mapped area")

    def size(self, key: str) -> int:
        """Registers of a struct/field of the area, by the symbol key of bridge.plc_types."""
        return _REGS[key]

    def offset(self, key: str) -> int:
        """First register of a struct/field of the area, by the symbol key of bridge.plc_types."""
        return getattr(self, _OFFSET[key])

    def writable(self, keys: frozenset[str]) -> list[range]:
        """Register ranges (offsets) a client with write permission for ``keys`` may write."""
        out = [range(self.offset(k), self.offset(k) + self.size(k)) for k in sorted(keys)
               if k not in ("shadow",)]
        if "shadow" in keys:
            out += [range(self.PAGE_CONTROL, self.PAGE_CONTROL + 4),
                    range(self.WINDOW, self.WINDOW + 4 * self.window_lreals)]
        return out

    def pages(self, n_lreals: int) -> list[tuple[int, int]]:
        """(page index, LREAL count) covering the first ``n_lreals`` of aShadow."""
        w = self.window_lreals
        return [(p, min(w, n_lreals - p * w)) for p in range((n_lreals + w - 1) // w)]


def to_registers(data: bytes) -> list[int]:
    """A little-endian memory image as Modbus registers (register k = bytes 2k, 2k+1)."""
    if len(data) % 2:
        data += b"\0"
    return np.frombuffer(data, dtype="<u2").tolist()


def from_registers(regs) -> bytes:
    """Modbus registers back to the memory image."""
    return np.asarray(regs, dtype="<u2").tobytes()
