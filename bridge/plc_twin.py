"""Python twin of the PLC logic in ``plc/``: GVL_CompTable, FB_CompTableManager, FB_CompTableLookup.

The mock PLCs (:mod:`pmcal.bridge.ads_mock`, :mod:`pmcal.bridge.modbus_mock`) expose one :class:`PlcTwin` through
their transport; a cycle thread calls :meth:`PlcTwin.cycle` like a TwinCAT task. The handshake:

1. the bridge writes ``stShadowHeader`` and ``aShadow`` (staging, never used for motion),
2. the bridge writes ``nCommitVersion := header.nTableVersion``,
3. the PLC copies shadow and header into the inactive buffer (snapshot), re-checks version, grid,
   limits, CRC-16, finiteness, ranges and steps, waits until motion allows (``motion_idle``), flips
   the active buffer, then writes ``eStatus`` and, last, ``nAckVersion``;
4. a rejection, a withdrawal (``nCommitVersion`` changed before the swap) or a swap time-out (motion
   did not allow it within ``commit_timeout_s``: a commit never lingers after its sender gave up)
   is acknowledged the same way with its status; the active table stays as it was;
5. ``nCommitVersion := 0`` returns the manager to idle and clears ``nAckVersion``.

Angles in degrees. Thread-safe: every access holds one lock, like ADS access between two task cycles.
"""

from __future__ import annotations

import threading
import time

import numpy as np

from pmcal.bridge.comptable import FORMAT_VERSION, NPHI_MAX, NTHETA_MAX, CompTable, crc16_ccitt, lookup
from pmcal.bridge.nominal import REFERENCE_NOMINAL_IK, REFERENCE_NONE, NominalReference
from pmcal.bridge.plc_types import (COMMIT_TIMEOUT_S, STAGING_LEASE_S, HEADER_SIZE, INTERFACE_VERSION, Header, LookupIn, LookupOut,
                              LookupResult, PlcState, State, Status, used_values)

#: Defect.kind of calib.comptable -> the PLC's status code
_DEFECT_STATUS = {
    "grid_size": Status.GRID_SIZE, "grid_limits": Status.GRID_LIMITS, "limits": Status.LIMITS,
    "version": Status.VERSION_MISMATCH, "stale_version": Status.STALE_VERSION,
    "not_finite": Status.NOT_FINITE, "out_of_range": Status.OUT_OF_RANGE, "step": Status.STEP_TOO_LARGE,
    "reference": Status.REFERENCE_MISMATCH,
}
#: the CRC self-test vector the ST code checks at start-up
CRC_SELFTEST = (b"123456789", 0x29B1)

_ZERO_HEADER = Header.unpack(bytes(HEADER_SIZE))


class PlcTwin:
    """The PLC side of the table hand-over and the motor-target lookup, as in ``plc/``.

    Symbols (GVL_CompTable) are exchanged as bytes with :meth:`read_symbol` / :meth:`write_symbol`
    under the keys of :data:`pmcal.bridge.plc_types.SYMBOLS`. ``motion_idle`` is the PLC input that allows the buffer swap.
    """

    def __init__(self, crc=crc16_ccitt, commit_timeout_s: float = COMMIT_TIMEOUT_S,
                 reference: NominalReference | None = None) -> None:
        self.lock = threading.RLock()
        #: GVL_CompTableParam.REF_*: the nominal geometry the PLC's F_CompTableNominalIk uses
        self.reference = reference or NominalReference.default()
        self._crc = crc
        self.motion_idle = True
        self.commit_timeout_s = commit_timeout_s
        self._wait_since = 0.0
        # staging area written by the bridge
        self.shadow_header = _ZERO_HEADER.pack()
        self.shadow = np.zeros((NPHI_MAX, NTHETA_MAX, 2), dtype="<f8")
        self.commit_version = 0
        self.staging_claim = 0
        self._owner = 0
        self._owner_since = 0.0
        self.staging_lease_s = STAGING_LEASE_S
        # double buffer
        self._buffers = [np.zeros_like(self.shadow), np.zeros_like(self.shadow)]
        self._headers = [_ZERO_HEADER, _ZERO_HEADER]
        self._active = 0
        self._last_commit = 0
        self._fsm = State.IDLE
        self._out = PlcState(0, 0, 0, Status.NONE, 0, State.IDLE)
        self.lookup_in = LookupIn(0.0, 0.0, 0).pack()
        self.lookup_out = LookupOut(0.0, 0.0, 0, 0, LookupResult.NO_TABLE).pack()
        self._selftest_ok = self._crc(CRC_SELFTEST[0]) == CRC_SELFTEST[1]
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # ---- symbol access (what ADS / the Modbus mapping reach) ------------------------------
    def read_symbol(self, key: str) -> bytes:
        with self.lock:
            if key == "interface_version":
                return INTERFACE_VERSION.to_bytes(2, "little")
            if key == "shadow_header":
                return self.shadow_header
            if key == "shadow":
                return self.shadow.tobytes()
            if key == "commit_version":
                return self.commit_version.to_bytes(4, "little")
            if key == "staging_claim":
                return self.staging_claim.to_bytes(4, "little")
            if key == "state":
                return self._out.pack()
            if key == "active_header":
                return self._headers[self._active].pack()
            if key == "lookup_in":
                return self.lookup_in
            if key == "lookup_out":
                return self.lookup_out
        raise KeyError(key)

    def write_symbol(self, key: str, data: bytes) -> None:
        """Write a symbol's bytes (sizes are checked by the transport, as the PLC would)."""
        with self.lock:
            if key == "shadow_header":
                self.shadow_header = bytes(data)
            elif key == "shadow":
                self.shadow = np.frombuffer(bytes(data), dtype="<f8").reshape(self.shadow.shape).copy()
            elif key == "commit_version":
                self.commit_version = int.from_bytes(data, "little")
            elif key == "staging_claim":
                self.staging_claim = int.from_bytes(data, "little")
            elif key == "lookup_in":
                self.lookup_in = bytes(data)
            else:
                raise PermissionError(f"{key} is written by the PLC only")

    def write_shadow_bytes(self, offset: int, data: bytes) -> None:
        """MEMCPY into ``aShadow`` at byte ``offset`` (the Modbus page adapter's store)."""
        with self.lock:
            flat = self.shadow.reshape(-1).view(np.uint8)
            flat[offset:offset + len(data)] = np.frombuffer(data, dtype=np.uint8)

    def read_shadow_bytes(self, offset: int, size: int) -> bytes:
        with self.lock:
            return self.shadow.reshape(-1).view(np.uint8)[offset:offset + size].tobytes()

    def corrupt_shadow(self) -> None:
        """Flip the lowest mantissa bit of the first staged value (fault injection: memory error)."""
        with self.lock:
            flat = self.shadow.reshape(-1).view(np.uint8)
            flat[0] ^= 0x01

    # ---- observation for tests and the twin loop -----------------------------------------
    @property
    def state(self) -> PlcState:
        with self.lock:
            return self._out

    def active_table(self) -> tuple[Header, np.ndarray]:
        """Header and used values (copy) of the active buffer."""
        with self.lock:
            h = self._headers[self._active]
            return h, used_values(h, self._buffers[self._active]).copy()

    # ---- the PLC task ---------------------------------------------------------------------
    def cycle(self) -> None:
        """One task cycle of FB_CompTableManager and FB_CompTableLookup."""
        with self.lock:
            out = self._out
            ack, status, active = out.ack_version, out.status, self._active
            if self._fsm == State.IDLE:
                if self.commit_version == 0:
                    self._last_commit, ack = 0, 0
                elif self.commit_version != self._last_commit:
                    self._last_commit = self.commit_version
                    spare = 1 - self._active
                    self._buffers[spare][...] = self.shadow          # snapshot: later writes don't matter
                    self._headers[spare] = Header.unpack(self.shadow_header)
                    self._fsm, status = State.CHECKING, Status.BUSY
            elif self.commit_version != self._last_commit:
                self._fsm, status, ack = State.IDLE, Status.WITHDRAWN, self._last_commit
            elif self._fsm == State.CHECKING:
                verdict = self._check(1 - self._active)
                if verdict is Status.OK:
                    self._fsm, self._wait_since = State.WAIT_MOTION, time.monotonic()
                else:
                    self._fsm, status, ack = State.IDLE, verdict, self._last_commit
            elif self._fsm == State.WAIT_MOTION and self.motion_idle:
                active = 1 - self._active
                self._active = active
                self._fsm, status, ack = State.IDLE, Status.OK, self._last_commit
            elif self._fsm == State.WAIT_MOTION and time.monotonic() - self._wait_since > self.commit_timeout_s:
                self._fsm, status, ack = State.IDLE, Status.SWAP_TIMEOUT, self._last_commit
            self._arbitrate()
            h = self._headers[active]
            self._out = PlcState(ack, h.table_version, (out.cycle + 1) & 0xFFFFFFFF, status, h.crc, self._fsm,
                                 self._owner)
            self._lookup()

    def _arbitrate(self) -> None:
        """FB_CompTableManager's staging arbitration: the first claim owns the staging area until it
        writes 0 (or stays silent for ``staging_lease_s`` while the manager is idle); other claims wait."""
        now = time.monotonic()
        if self._owner == 0:
            if self.staging_claim != 0:
                self._owner, self._owner_since = self.staging_claim, now
        elif self.staging_claim == 0:
            self._owner = 0
        elif self._fsm != State.IDLE or self.commit_version != 0:
            self._owner_since = now                                   # the owner's commit is in progress
        elif now - self._owner_since > self.staging_lease_s:
            self._owner, self._owner_since = self.staging_claim, now  # lease expired: the latest claim

    def _check(self, idx: int) -> Status:
        """FB_CompTableCheck on buffer ``idx``: the same checks and order as the ST code."""
        if not self._selftest_ok:
            return Status.CRC_SELFTEST
        h = self._headers[idx]
        if h.format_version != FORMAT_VERSION:
            return Status.FORMAT_VERSION
        if h.table_version != self._last_commit:
            return Status.VERSION_MISMATCH
        if not (2 <= h.n_phi <= NPHI_MAX and 2 <= h.n_theta <= NTHETA_MAX):
            return Status.GRID_SIZE
        if h.reference == REFERENCE_NOMINAL_IK:
            if h.reference_crc != self._crc(self.reference.pack()):
                return Status.REFERENCE_MISMATCH
            ref = self.reference
        elif h.reference == REFERENCE_NONE:
            ref = None
        else:
            return Status.REFERENCE_MISMATCH
        values = used_values(h, self._buffers[idx])
        table = CompTable(machine=h.machine, version=h.table_version, values=values, reference=ref, **h.limits())
        defect = table.header_defect(active_version=self._headers[self._active].table_version)
        if defect is not None and defect.kind != "machine":       # the PLC does not look at the name
            return _DEFECT_STATUS[defect.kind]
        if self._crc(table.data_bytes()) != h.crc:
            return Status.CRC_MISMATCH
        defect = table.data_defect()
        return Status.OK if defect is None else _DEFECT_STATUS[defect.kind]

    def _lookup(self) -> None:
        """FB_CompTableLookup for the request in ``stLookupIn`` (answers once per new ``nSeq``)."""
        if self.lookup_in[16:20] == self.lookup_out[16:20]:      # nSeq answered already
            return
        req = LookupIn.unpack(self.lookup_in)
        h = self._headers[self._active]
        if h.table_version == 0:
            out = LookupOut(0.0, 0.0, req.seq, 0, LookupResult.NO_TABLE)
        else:
            ref = self.reference if h.reference == REFERENCE_NOMINAL_IK else None
            m, inside = lookup(used_values(h, self._buffers[self._active]), ref, (h.phi_min_deg, h.phi_max_deg),
                               (h.theta_min_deg, h.theta_max_deg), req.phi_deg, req.theta_deg)
            res = LookupResult.OK if bool(inside) else LookupResult.OUT_OF_GRID
            m = m if bool(inside) else np.zeros(2)
            out = LookupOut(float(m[0]), float(m[1]), req.seq, h.table_version, res)
        self.lookup_out = out.pack()

    # ---- cyclic task ----------------------------------------------------------------------
    def start(self, period_s: float = 0.001, lifetime_s: float = 600.0, before=(), after=()) -> None:
        """Run :meth:`cycle` every ``period_s`` in a daemon thread, with ``before``/``after`` hooks.

        The hooks model the I/O mapping of a task (e.g. the Modbus area copied in and out).

        The task ends by itself after ``lifetime_s`` (a mock never outlives its test session).
        """
        if self._thread is not None:
            return
        self._stop.clear()
        deadline = time.monotonic() + lifetime_s

        def task() -> None:
            while not self._stop.is_set() and time.monotonic() < deadline:
                with self.lock:
                    for hook in before:
                        hook()
                    self.cycle()
                    for hook in after:
                        hook()
                self._stop.wait(period_s)

        self._thread = threading.Thread(target=task, name="plc-twin-task", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None

    def restart(self) -> None:
        """A power cycle or cold reset of the PLC (the task must be stopped around it).

        Volatile data start from zero: staging (``stShadowHeader``, ``aShadow``), ``nCommitVersion``,
        the staging claim, the manager's step, the lookup. The double buffer, its headers and
        ``nActive`` are ``VAR_GLOBAL PERSISTENT`` (GVL_CompTable), so the active table, its version
        and with it the version order survive. At start-up FB_CompTableManager re-checks the active
        table (CRC-16 against its header, then values, ranges and steps, as for a commit); a damaged
        persistent table is dropped (``NO_TABLE``, status ``CRC_MISMATCH`` or the check's verdict)
        rather than used.
        """
        with self.lock:
            self.shadow_header = _ZERO_HEADER.pack()
            self.shadow[...] = 0.0
            self.commit_version = self.staging_claim = self._owner = 0
            self._last_commit, self._fsm = 0, State.IDLE
            self.lookup_in = LookupIn(0.0, 0.0, 0).pack()
            self.lookup_out = LookupOut(0.0, 0.0, 0, 0, LookupResult.NO_TABLE).pack()
            self._selftest_ok = self._crc(CRC_SELFTEST[0]) == CRC_SELFTEST[1]
            status = self._startup_check()
            h = self._headers[self._active]
            self._out = PlcState(0, h.table_version, 0, status, h.crc, State.IDLE, 0)

    def _startup_check(self) -> Status:
        """FB_CompTableManager's first cycles: the persistent active table checked like a commit."""
        h = self._headers[self._active]
        if h.table_version == 0:
            return Status.NONE
        self._last_commit = h.table_version
        saved = self._headers[self._active]
        self._headers[self._active] = _ZERO_HEADER          # "newer than active": compare with nothing
        other = 1 - self._active
        self._headers[other], spare_header = h, self._headers[other]
        self._buffers[other], spare = self._buffers[self._active], self._buffers[other]
        try:
            verdict = self._check(other)
        finally:
            self._buffers[other], self._headers[other] = spare, spare_header
            self._headers[self._active] = saved
            self._last_commit = 0
        if verdict is not Status.OK:
            self._headers[self._active] = _ZERO_HEADER      # never move with a damaged table
        return verdict

    def corrupt_persistent(self) -> None:
        """Flip a bit of the active table in persistent memory (fault injection for the start-up check)."""
        with self.lock:
            self._buffers[self._active].reshape(-1).view(np.uint8)[3] ^= 0x10

    def seed(self, table: CompTable) -> None:
        """Make ``table`` the active table directly (commissioning: the 'last good version')."""
        with self.lock:
            idx = 1 - self._active
            self._buffers[idx][...] = 0.0
            self._buffers[idx][:table.n_phi, :table.n_theta, :] = table.values
            self._headers[idx] = Header.of(table)
            self._active = idx
            self._out = PlcState(self._out.ack_version, table.version, self._out.cycle, Status.OK,
                                 table.crc16(), self._fsm, self._owner)

