"""The table hand-over, independent of the transport: validate, check, stage, read back, commit, ack.

:func:`push` drives any :class:`PlcLink` (ADS in :mod:`pmcal.bridge.ads`, Modbus in :mod:`pmcal.bridge.modbus`):

1. validate the table locally (before connecting);
2. open the link, check the PLC interface, read the PLC state;
3. refuse a version that is not newer than the active one (before anything is written);
4. claim the staging area with a random token (``nStagingClaim := token``, bit 31 set) and wait until the
   PLC grants it (``nStagingOwner = token``; at most ``claim_timeout_s``: the lease of a silent owner plus a
   margin); read the active version again (what this push replaces) and wait for the PLC to be idle;
5. stage header and table into the shadow buffer, read both back and compare bit for bit;
6. commit by writing the token (``nCommitToken := token``: the fencing token; a client that lost the staging
   area cannot commit); wait for the PLC's acknowledgement (``nAckToken = token``, time-out
   ``ack_timeout_s``); on time-out withdraw the commit (``nCommitToken := NOT token``: every owner write
   carries the token, a former owner's late write changes nothing) and report the version that stays active. A PLC
   still re-checking its persistent table after a restart answers ``PLC_STARTING``: commit again with
   backoff for up to ``start_wait_s``.

Link errors (and read-back mismatches) close the link and restart from step 2, at most ``attempts``
times; if a commit was sent before the link broke and the PLC meanwhile activated exactly this table,
the restart reports success instead of committing twice. A PLC rejection is never retried.
Every call ends with one audit line (JSON) carrying the SHA-256 of the bytes sent.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

from pmcal.bridge.comptable import CompTable
from pmcal.bridge.errors import AckTimeout, BridgeError, LinkError, ReadbackMismatch, Rejected, StagingBusy
from pmcal.bridge.link import PlcLink
from pmcal.bridge.plc_types import (HEADER_SIZE, LREAL_SIZE, STAGING_LEASE_S, Header, PlcState, State, Status,
                                   done_value, new_token, shadow_rows)
from pmcal.errors import InputError


@dataclass(frozen=True)
class PushOptions:
    """Retry and timing policy of :func:`push` (seconds)."""

    attempts: int = 3
    ack_timeout_s: float = 5.0
    idle_timeout_s: float = 2.0
    poll_s: float = 0.0005
    retry_pause_s: float = 0.05
    dry_run: bool = False
    #: keep re-committing after SWAP_TIMEOUT (the machine moving) until this long has passed, s
    wait_motion_s: float = 0.0
    #: wait this long for the staging area held by another client (its lease plus a margin), s
    claim_timeout_s: float = STAGING_LEASE_S + 5.0
    #: keep committing again (backoff 0.1 s doubling to 2 s) while the PLC answers PLC_STARTING, s
    start_wait_s: float = 15.0


@dataclass
class PushReport:
    """Outcome of one :func:`push`; ``audit_line()`` is what goes to the audit log."""

    transport: str
    target: str
    machine: str
    version: int
    crc32: str
    result: str = "failed"           # ok | already_active | dry_run | rejected | refused | failed
    status: str = ""                 # PLC status after the ack
    previous_version: int | None = None
    active_version: int | None = None
    attempts: int = 0
    bytes_sent: int = 0
    sha256_sent: str = ""
    dry_run: bool = False
    message: str = ""
    timings_s: dict = field(default_factory=dict)

    def audit_line(self) -> str:
        doc = {"time": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds"),
               "event": "push", **asdict(self)}
        doc["timings_s"] = {k: round(v, 6) for k, v in self.timings_s.items()}
        return json.dumps(doc, sort_keys=False)


def push(link: PlcLink, table: CompTable, options: PushOptions = PushOptions(),
         audit_path: str | os.PathLike | None = None) -> PushReport:
    """Send ``table`` to the PLC behind ``link`` and make it active; see the module docstring.

    Raises :class:`InputError` for a bad or stale table (nothing written), :class:`BridgeError`
    subclasses for transfer failures (with ``exc.report``). Returns the report on success.
    """
    table.validate()
    if audit_path is not None and not options.dry_run:
        check_writable(audit_path, "--audit")          # before anything reaches the PLC
    run = _Run(link, table, options, PushReport(link.transport, link.target, table.machine, int(table.version),
                                                f"0x{table.crc32():08X}", dry_run=options.dry_run))
    t0 = time.perf_counter()
    try:
        for attempt in range(1, max(1, options.attempts) + 1):
            run.rep.attempts = attempt
            try:
                run.attempt()
                return run.rep
            except LinkError as exc:
                link.close()
                if attempt >= options.attempts:
                    raise type(exc)(f"{exc} (gave up after {attempt} attempt{'s' * (attempt > 1)})") from exc
                time.sleep(options.retry_pause_s)
        raise AssertionError("unreachable")
    except InputError as exc:
        run.rep.result, run.rep.message = "refused", str(exc)
        raise
    except BridgeError as exc:
        rep = run.rep
        if not run.commit_sent:
            note = "; nothing committed, the active table is unchanged"
        else:
            note = run.abandon() if not run.acknowledged else ""
        if rep.result in ("ok", "already_active"):          # a late commit made it after all
            return rep
        rep.result = "rejected" if isinstance(exc, Rejected) else "failed"
        rep.message = f"{exc}{note}"
        failure = type(exc)(rep.message)
        failure.report = rep
        raise failure from exc
    finally:
        run.release()
        link.close()
        run.rep.timings_s["total"] = time.perf_counter() - t0
        if audit_path is not None:
            append_audit(audit_path, run.rep.audit_line())


@dataclass
class _Run:
    """One :func:`push`: the images to send and whether a commit may already have reached the PLC."""

    link: PlcLink
    table: CompTable
    opt: PushOptions
    rep: PushReport
    commit_sent: bool = False
    acknowledged: bool = False
    owned: bool = False

    def __post_init__(self) -> None:
        self.header = Header.of(self.table).pack()
        self.rows = shadow_rows(self.table)
        self.token = new_token()                       # this push's session token (bit 31 set)

    def claim(self) -> None:
        """Own the PLC's staging area (``nStagingOwner = token``) or raise :class:`StagingBusy`
        (:func:`claim_area`, waiting up to ``claim_timeout_s``)."""
        claim_area(self.link, self.token, self.opt.claim_timeout_s, self.opt.poll_s)
        self.owned = True

    def lost(self) -> bool:
        """The PLC names another client (or nobody) as the staging owner: this push lost the area.

        False when the state cannot be read: then this push may still own it and acts as the owner.
        """
        try:
            return self.link.read_state().staging_owner != self.token
        except BridgeError:
            return False

    def release(self) -> None:
        """``nStagingClaim := NOT token`` if this push owns the staging area (best effort, :func:`release_area`)."""
        if not self.owned:
            return
        for reopen in (False, True):                   # after a broken link: once more on a fresh one
            try:
                if reopen:
                    self.link.close()
                    self.link.open()
                if self.lost():                       # lease lost: the area is someone else's now
                    self.owned = False
                    return
                release_area(self.link, self.token, self.opt.idle_timeout_s, self.opt.poll_s)
                self.owned = False
                return
            except (BridgeError, OSError):
                continue

    def abandon(self) -> str:
        """After a failure with a commit possibly pending: withdraw it and say what is active.

        Best effort on a fresh connection. If the PLC activated exactly this table meanwhile, the
        report turns into success ("already_active").
        """
        link, version = self.link, int(self.table.version)
        try:
            link.close()
            link.open()
            try:
                owner = link.read_state().staging_owner
            except BridgeError:                       # unreadable: act as the owner, on a fresh connection
                owner = self.token
                link.close()
                link.open()
            if owner == self.token:                   # only the owner's NOT token withdraws (a lost lease
                link.write_commit(done_value(self.token))   # already dropped this push's commit)
        except BridgeError:
            return f"; could not withdraw the commit of version {version} (link down): the PLC drops it " \
                   "unless it passes its checks and motion allows the swap before its commit time-out"
        try:
            st = _settle(link, self.opt)
        except BridgeError:
            return f"; commit of version {version} withdrawn, PLC state unreadable"
        self.rep.active_version, self.rep.status = st.active_version, _name(st.status)
        if st.active_version == version and st.active_crc == self.table.crc32() \
                and link.read_active_header() == self.header:
            self.rep.result = "already_active"
            self.rep.message = f"version {version} active (the acknowledgement was lost, the table was not)"
            return ""
        return f"; commit withdrawn, active version stays {st.active_version}"

    def attempt(self) -> None:
        link, opt, rep = self.link, self.opt, self.rep
        version, crc = int(self.table.version), self.table.crc32()
        t = time.perf_counter()
        link.open()
        link.check_interface()
        st = link.read_state()
        rep.timings_s["connect_check"] = time.perf_counter() - t
        if rep.previous_version is None:
            rep.previous_version = st.active_version
        rep.active_version = st.active_version
        if st.active_version == version and st.active_crc == crc and link.read_active_header() == self.header:
            rep.result, rep.status = "already_active", Status.OK.name
            rep.message = (f"version {version} became active before the link was lost; not committed twice"
                           if self.commit_sent else f"version {version} with this content is already active")
            return
        self.table.validate(active_version=st.active_version)
        if opt.dry_run:
            would = b"".join(link.payload(self.header, self.rows))
            rep.result, rep.sha256_sent = "dry_run", hashlib.sha256(would).hexdigest()
            rep.message = (f"dry run: would stage {len(would)} bytes (sha256 {rep.sha256_sent[:16]}) and commit "
                           f"version {version} (active version {st.active_version}); nothing written")
            return
        # own the staging area (the PLC dropped any commit of a former owner), wait for an idle manager;
        # the active table now is the one this push replaces: only the owner changes it from here on
        self.claim()
        link.write_commit(done_value(self.token))      # a commit of this push from a lost link: withdrawn
        st = _wait(link, _idle, opt.idle_timeout_s, opt.poll_s, "PLC manager did not become idle after the claim")
        rep.previous_version = rep.active_version = st.active_version
        self.table.validate(active_version=st.active_version)
        # stage and read back
        t = time.perf_counter()
        sent_header, sent_rows = link.stage(self.header, self.rows)
        rep.timings_s["stage"] = time.perf_counter() - t
        rep.bytes_sent = len(sent_header) + len(sent_rows)
        rep.sha256_sent = hashlib.sha256(sent_header + sent_rows).hexdigest()
        t = time.perf_counter()
        back_header, back_rows = link.read_back(len(sent_rows))
        rep.timings_s["readback"] = time.perf_counter() - t
        _compare(sent_header, sent_rows, back_header, back_rows, self.table.n_motors)
        # commit and wait for the acknowledgement
        t = time.perf_counter()
        if link.read_state().staging_owner != self.token:
            self.owned = False
            raise StagingBusy("lost the PLC's staging area before the commit (its lease ended while this push was "
                              "silent); nothing committed")
        self.commit_sent = True
        motion_deadline = time.monotonic() + opt.wait_motion_s
        start_deadline, backoff = time.monotonic() + opt.start_wait_s, 0.1
        while True:
            link.write_commit(self.token)
            st = self._await_ack(version, crc)
            if st.status == Status.PLC_STARTING and time.monotonic() < start_deadline:
                # the PLC re-checks its persistent table after a restart: commit again, with backoff
                time.sleep(backoff)
                backoff = min(2.0 * backoff, 2.0)
            elif st.status != Status.SWAP_TIMEOUT or time.monotonic() >= motion_deadline:
                break
            # commit again: after PLC_STARTING, or SWAP_TIMEOUT (the machine kept moving) with --wait-motion
            link.write_commit(done_value(self.token))
            _wait(link, _idle, opt.idle_timeout_s, opt.poll_s, "PLC manager did not become idle after clearing nCommitToken")
        rep.timings_s["commit_ack"] = time.perf_counter() - t
        self.acknowledged = True
        rep.active_version, rep.status = st.active_version, _name(st.status)
        _release(link, self.token)
        if st.status.activated and st.active_version == version and st.active_crc == crc:
            rep.result = "ok"
            rep.message = f"version {version} active (was {rep.previous_version})"
            if st.status == Status.OK_NOT_PERSISTED:
                rep.message += ("; WARNING: the PLC could not save it (WritePersistentData failed): a power cut "
                                "without UPS would restore the previous table")
            return
        reason = _REASONS.get(st.status, "see plc/README.md")
        if st.status == Status.SWAP_TIMEOUT:
            waited = f" and {opt.wait_motion_s:g} s of --wait-motion" if opt.wait_motion_s > 0 else ""
            reason += f"{waited}; stop the machine, or wait longer with --wait-motion S"
        raise Rejected(f"PLC rejected version {version}: {_name(st.status)} ({reason}); "
                       f"active version stays {st.active_version}")

    def _await_ack(self, version: int, crc: int) -> PlcState:
        """The PLC's acknowledgement of ``version``; on time-out withdraw and say what the PLC was doing."""
        link, opt, rep = self.link, self.opt, self.rep
        try:
            return _wait(link, lambda s: s.ack_token == self.token and s.state in _RESTING, opt.ack_timeout_s,
                         opt.poll_s, "")
        except AckTimeout:
            before = link.read_state()                  # what the PLC was doing, before the withdrawal
            st = _settle(link, opt) if self.lost() else _withdraw(link, opt, self.token)
            self.acknowledged = True                    # settled: withdrawn (or swapped just before)
            rep.active_version, rep.status = st.active_version, _name(st.status)
            if st.active_version == version and st.active_crc == crc:
                return st
            doing = _DOING.get(before.state, f"state {_name(before.state)}")
            raise AckTimeout(f"PLC did not acknowledge version {version} within {opt.ack_timeout_s:g} s: {doing}; "
                             f"commit withdrawn, active version stays {st.active_version}") from None


#: manager states in which no commit is in progress
_RESTING = (State.IDLE, State.STARTING)


def _idle(st: PlcState) -> bool:
    """No commit in progress and no acknowledgement pending."""
    return st.ack_token == 0 and st.state in _RESTING


_DOING = {
    State.STARTING: "the PLC is re-checking its persistent table after a restart (STARTING)",
    State.PERSISTING: "the table is active and the PLC is saving it (PERSISTING; raise --ack-timeout)",
    State.WAIT_MOTION: "the table passed the PLC's checks and waits for the machine to stop (WAIT_MOTION; "
                       "stop the machine, or use --wait-motion S)",
    State.CHECKING: "the PLC was still checking the table (CHECKING; raise --ack-timeout)",
    State.IDLE: "the PLC's manager is idle and did not take the commit (state IDLE)",
}

_REASONS = {
    Status.FORMAT_VERSION: "unknown table format version",
    Status.VERSION_MISMATCH: "commit version differs from the staged header",
    Status.STALE_VERSION: "not newer than the active table",
    Status.GRID_SIZE: "grid size outside the PLC arrays",
    Status.GRID_LIMITS: "grid limits not finite or not increasing",
    Status.LIMITS: "motor limits or max step invalid (a correction table: bounds beyond the PLC's "
                   "CORRECTION_ABS_MAX)",
    Status.CRC_MISMATCH: "CRC of the staged data differs from the header: data damaged after staging",
    Status.NOT_FINITE: "NaN or infinite value",
    Status.OUT_OF_RANGE: "value outside the motor limits (a correction table: outside its correction bounds)",
    Status.STEP_TOO_LARGE: "step between neighbouring nodes too large",
    Status.CRC_SELFTEST: "the PLC's CRC function fails its self-test",
    Status.WITHDRAWN: "commit withdrawn by another client",
    Status.SWAP_TIMEOUT: "motion did not allow the buffer swap within the PLC's commit time-out",
    Status.PLC_STARTING: "the PLC kept re-checking its persistent table after a restart; try again",
    Status.REFERENCE_MISMATCH: "the table's nominal-IK reference differs from the PLC's GVL_CompTableParam.REF_*, "
                               "or the PLC program does not know the table's reference kind",
    Status.MACHINE_MISMATCH: "the table names another machine than the PLC's GVL_CompTableParam.MACHINE",
    Status.KIND_MISMATCH: "the table's kind (motor commands or corrections) is not the one the PLC's motion code "
                          "uses (GVL_CompTableParam.CORRECTIONS)",
    Status.MOTORS_MISMATCH: "the table has another number of motors than the PLC's GVL_CompTableParam.NMOTORS",
    Status.NOT_CONFIGURED: "the PLC is not configured for a machine (GVL_CompTableParam.MACHINE, NMOTORS): it "
                           "serves no table",
}


def _name(v) -> str:
    return v.name if hasattr(v, "name") else str(v)


def _wait(link: PlcLink, ready: Callable[[PlcState], bool], timeout_s: float, poll_s: float,
          what: str) -> PlcState:
    """Poll the PLC state until ``ready`` or the time-out (bounded loop)."""
    deadline = time.monotonic() + timeout_s
    while True:
        st = link.read_state()
        if ready(st):
            return st
        if time.monotonic() >= deadline:
            raise AckTimeout(what or "time-out")
        time.sleep(poll_s)


def claim_area(link: PlcLink, token: int, timeout_s: float, poll_s: float) -> None:
    """Own the PLC's staging area with ``token`` (``nStagingOwner = token``) or raise :class:`StagingBusy`.

    The PLC grants the area to one claim and keeps it until its owner writes NOT token, or until the
    owner has been silent for the PLC's staging lease while another client claims. So this waits up to
    ``timeout_s`` (lease + margin), writing the claim again whenever the area is free.
    """
    deadline = time.monotonic() + timeout_s
    link.write_claim(token)
    while True:
        st = link.read_state()
        if st.staging_owner == token:
            return
        if st.staging_owner == 0:
            link.write_claim(token)                   # the area is free: claim (again, after a release)
        if time.monotonic() >= deadline:
            raise StagingBusy(f"another client is staging a table on this PLC (session 0x{st.staging_owner:08X}) "
                              f"and kept it for {timeout_s:g} s; nothing written (if that client is gone "
                              "and cannot be waited for: pmcal plc unlock)")
        time.sleep(max(poll_s, 0.002))


def release_area(link: PlcLink, token: int, timeout_s: float, poll_s: float) -> bool:
    """Release the staging area owned with ``token`` (``nStagingClaim := NOT token``) and wait until the
    PLC has seen it, writing it again (a claim of another client may overwrite it first); True if released."""
    deadline = time.monotonic() + timeout_s
    while True:
        link.write_claim(done_value(token))
        try:
            _wait(link, lambda s: s.staging_owner != token, 0.1, poll_s, "")
            return True
        except AckTimeout:
            if time.monotonic() >= deadline:
                return False


def _withdraw(link: PlcLink, opt: PushOptions, token: int) -> PlcState:
    """Withdraw the owner's commit after an ack time-out and return the settled PLC state."""
    link.write_commit(done_value(token))
    return _settle(link, opt)


def _settle(link: PlcLink, opt: PushOptions) -> PlcState:
    """The PLC state once the manager is idle again (or as it is after ``idle_timeout_s``)."""
    try:
        return _wait(link, lambda s: s.state in _RESTING, opt.idle_timeout_s, opt.poll_s, "")
    except AckTimeout:
        return link.read_state()


def _release(link: PlcLink, token: int) -> None:
    """After the acknowledgement: ``nCommitToken := NOT token`` clears it, the manager is idle (best effort)."""
    try:
        link.write_commit(done_value(token))
    except BridgeError:
        pass


def _compare(sent_header: bytes, sent_rows: bytes, back_header: bytes, back_rows: bytes, n_motors: int) -> None:
    """Raise :class:`ReadbackMismatch` naming the first differing header byte or table node."""
    if back_header != sent_header:
        pos = next(i for i in range(HEADER_SIZE) if i >= len(back_header) or back_header[i] != sent_header[i])
        raise ReadbackMismatch(f"read-back of the staged header differs at byte {pos}")
    if back_rows != sent_rows:
        n = min(len(back_rows), len(sent_rows))
        pos = next((i for i in range(0, n, LREAL_SIZE)
                    if back_rows[i:i + LREAL_SIZE] != sent_rows[i:i + LREAL_SIZE]), n)
        node, m = divmod(pos // LREAL_SIZE, n_motors)
        raise ReadbackMismatch(f"read-back of the staged table differs at value {pos // LREAL_SIZE} (node {node} "
                               f"in memory order, motor m{m + 1})")


def check_writable(path: str | os.PathLike, what: str, replace: bool = False) -> None:
    """Raise :class:`InputError` unless ``path`` can be appended to (or created in its folder).

    ``replace``: the file is written atomically (a new file in its folder, then renamed), so the
    folder must be writable. Called before the first write to the PLC, so a local failure never
    follows a committed table.
    """
    p = Path(path)
    if p.is_dir():
        raise InputError("is a folder, not a file", file=str(p), field=what)
    if p.exists() and not replace:
        ok = os.access(p, os.W_OK)
    else:
        folder = next((d for d in [p.parent, *p.parent.parents] if d.exists()), Path("."))
        ok = folder.is_dir() and os.access(folder, os.W_OK | os.X_OK)
    if not ok:
        raise InputError("cannot be written (read-only file or folder); nothing was sent to the PLC",
                         file=str(p), field=what)


def append_audit(path: str | os.PathLike, line: str) -> None:
    """Append one line to the audit log (created if missing), flushed to disk."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    with open(p, "a", encoding="utf-8") as fh:
        fh.write(line.rstrip("\n") + "\n")
        fh.flush()
        os.fsync(fh.fileno())
