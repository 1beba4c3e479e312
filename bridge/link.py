"""What a transport offers the hand-over (:class:`PlcLink`) and the part both transports share.

A transport implements its primitives on PLC memory images (bytes, little-endian, the layouts of
:mod:`pmcal.bridge.plc_types`): ``open``, ``close``, ``check_interface``, ``read_symbol``/``write_symbol``
for the small GVL_CompTable variables, and ``stage``/``read_back`` (and, if it pads, ``payload``)
for the table itself.
:class:`LinkBase` builds the rest on them (state, commit, motor-target lookup).
"""

from __future__ import annotations

import time
from typing import Protocol

from pmcal.bridge.errors import AckTimeout
from pmcal.bridge.plc_types import LookupIn, LookupOut, PlcState


class PlcLink(Protocol):
    """What :func:`pmcal.bridge.transfer.push` and the twin loop need from a transport."""

    transport: str          # "ads" or "modbus"
    target: str             # where, for messages and the audit

    def open(self) -> None: ...
    def close(self) -> None: ...
    def check_interface(self) -> None: ...
    def payload(self, header: bytes, rows: bytes) -> tuple[bytes, bytes]: ...
    def read_state(self) -> PlcState: ...
    def read_active_header(self) -> bytes: ...
    def write_commit(self, token: int) -> None: ...
    def write_claim(self, token: int) -> None: ...
    def stage(self, header: bytes, rows: bytes) -> tuple[bytes, bytes]: ...
    def read_back(self, data_size: int) -> tuple[bytes, bytes]: ...
    def lookup(self, *x: float, timeout_s: float = 1.0) -> LookupOut: ...


class LinkBase:
    """State, commit and lookup on top of a transport's ``read_symbol``/``write_symbol``."""

    transport = ""
    target = ""
    _lookup_seq: int | None = None

    def read_symbol(self, key: str) -> bytes:
        raise NotImplementedError

    def write_symbol(self, key: str, data: bytes) -> None:
        raise NotImplementedError

    def open(self) -> None:
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError

    def payload(self, header: bytes, rows: bytes) -> tuple[bytes, bytes]:
        """The exact bytes :meth:`stage` sends for a header and the table rows (default: as they are)."""
        return header, rows

    def read_state(self) -> PlcState:
        """ST_CompTableState: ack/active version, status, active CRC, manager state, cycle counter."""
        return PlcState.unpack(self.read_symbol("state"))

    def read_active_header(self) -> bytes:
        return self.read_symbol("active_header")

    def write_commit(self, token: int) -> None:
        """``nCommitToken := token``: the staging owner's token commits the staged table; its complement
        (:func:`pmcal.bridge.plc_types.done_value`) withdraws the commit or clears the acknowledgement."""
        self.write_symbol("commit", int(token).to_bytes(4, "little"))

    def write_claim(self, token: int) -> None:
        """``nStagingClaim := token`` (a session token claims the staging area; its complement releases it)."""
        self.write_symbol("staging_claim", int(token).to_bytes(4, "little"))

    def lookup(self, *x: float, timeout_s: float = 1.0) -> LookupOut:
        """Motor targets (deg or mm) for the task point ``x`` (1 to 3 coordinates in the table's axis units,
        e.g. ``lookup(phi_deg, theta_deg)``) from FB_CompTableLookup; waits for the answer."""
        if self._lookup_seq is None:
            self._lookup_seq = LookupOut.unpack(self.read_symbol("lookup_out")).seq
        self._lookup_seq = (self._lookup_seq + 1) & 0xFFFFFFFF or 1
        self.write_symbol("lookup_in", LookupIn(tuple(float(v) for v in x), self._lookup_seq).pack())
        deadline = time.monotonic() + timeout_s
        while True:
            out = LookupOut.unpack(self.read_symbol("lookup_out"))
            if out.seq == self._lookup_seq:
                return out
            if time.monotonic() >= deadline:
                raise AckTimeout(f"PLC did not answer lookup request {self._lookup_seq} within {timeout_s:g} s")
            time.sleep(0.0002)

    def __enter__(self):
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()
