"""``pmcal push``, ``pmcal mock-plc`` and ``pmcal loop``: the compensation table to the PLC and back.

- ``pmcal push TABLE --ads NETID@HOST[:PORT] | --modbus HOST[:PORT] [--dry-run]`` sends a table
  (JSON or CSV, docs/compensation_table.md) and makes it active; exit 0 on success, 2 for a bad or
  stale table (nothing written), 1 for a transfer failure, 3 when the PLC rejects the table.
- ``pmcal mock-plc --ads|--modbus`` runs a mock PLC on 127.0.0.1 for manual trials.
- ``pmcal plc status|verify|unlock`` asks the PLC what it runs, or frees its staging area.
- ``pmcal loop`` puts the digital twin in the loop (see :mod:`pmcal.apps.ocpm.plc_loop`; a machine folder's:
  :mod:`pmcal.apps.chain_loop`).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

from pmcal.bridge.simulator.mock import RESTART_S
from pmcal.commands.options import Command, CommandSet
from pmcal.errors import InputError
from pmcal.fileio import atomic_write

MAX_MOCK_SECONDS = 24 * 3600.0


def register(sub: CommandSet) -> None:
    p = sub.add_parser("push", help="send a compensation table to the PLC (ADS or Modbus TCP)")
    p.add_argument("table", metavar="TABLE", help="compensation table, .json or .csv", role="input")
    _target_args(p)
    p.add_argument("--dry-run", action="store_true",
                   help="connect, check the interface and the table, write nothing")
    p.add_argument("--attempts", type=int, default=3, help="transfer attempts on link errors (default 3)")
    p.add_argument("--ack-timeout", type=float, default=5.0, metavar="S",
                   help="wait this long for the PLC's acknowledgement (default 5 s; keep it above the PLC's "
                        "commit time-out, FB_CompTableManager.tCommitTimeout, 4 s)")
    p.add_argument("--wait-motion", type=float, default=0.0, metavar="S",
                   help="if the machine is moving (the PLC reports WAIT_MOTION/SWAP_TIMEOUT), keep the commit "
                        "up for this long, s (default 0: report it at once)")
    p.add_argument("--audit", default=None, metavar="FILE", role="output",
                   help="audit log to append to (default: bridge_audit.log beside TABLE)")
    p.add_argument("--no-audit", action="store_true", help="write no audit line")
    p.add_argument("--json", default=None, metavar="REPORT.json", help="also write the push report as JSON",
                   role="output", suffixes=(".json",))
    p.add_argument("--force", action="store_true",
                   help="push a table made from a calibration that identify flagged not usable")
    p.set_defaults(func=cmd_push, prepare=_audit_default)

    m = sub.add_parser("mock-plc", help="run a mock TwinCAT PLC on 127.0.0.1 for manual trials")
    g = m.add_mutually_exclusive_group(required=True)
    g.add_argument("--ads", action="store_true", help="serve GVL_CompTable over ADS")
    g.add_argument("--modbus", action="store_true", help="serve the Modbus TCP area")
    m.add_argument("--port", type=int, default=0, help="TCP port (default: a free one)")
    m.add_argument("--seconds", type=float, default=600.0, help="stop after this long (default 600 s)")
    m.add_argument("--table", default=None, metavar="TABLE", help="make this table active at start", role="input")
    m.add_argument("--fault", action="append", default=[], metavar="KIND@POINT[*N]",
                   help="inject a fault, e.g. drop@mid_stage or delay@ack_wait*1 (repeatable)")
    m.add_argument("--motion-busy", action="store_true", help="the machine never stands still (no swap)")
    m.add_argument("--cycle-ms", type=float, default=1.0, help="PLC task cycle, ms (default 1)")
    m.add_argument("--restart-after", type=float, default=None, metavar="S",
                   help="restart the mock PLC cleanly once after S seconds (as with a UPS: persistent data "
                        "saved, staging lost)")
    m.add_argument("--power-cut-after", type=float, default=None, metavar="S",
                   help="cut the power once after S seconds, as on a CX without UPS: connections drop, RAM "
                        "and PERSISTENT data not saved by WritePersistentData are lost, then the PLC restarts "
                        "on the same address")
    m.add_argument("--restart-s", type=float, default=RESTART_S, metavar="S",
                   help=f"how long a restart or power cut keeps the PLC away, s (default {RESTART_S:g}, as a "
                        "CX booting; the last second the router answers ADS error 6)")
    m.add_argument("--route", action="append", default=None, metavar="NETID",
                   help="ADS: accept only clients with this AMS NetID (repeatable); frames from others are "
                        "dropped without an answer, as by a TwinCAT router without that route (the client "
                        "times out: ADS error 1861)")
    m.add_argument("--staging-lease", type=float, default=None, metavar="S",
                   help="shorten the PLC's staging lease to S seconds (studies of killed clients)")
    m.add_argument("--plc-machine", default=None, metavar="NAME",
                   help="GVL_CompTableParam.MACHINE of the mock: the machine whose tables it accepts (default: "
                        "the --table's machine, else the --machine's, else ocpm_2dof); '' is the shipped, "
                        "unconfigured PLC")
    m.add_argument("--plc-motors", type=int, default=None, metavar="N",
                   help="GVL_CompTableParam.NMOTORS: motors of a table it accepts, 0..6 (default: the --table's, "
                        "else the --machine's, else 2)")
    m.add_argument("--plc-corrections", action=argparse.BooleanOptionalAction, default=None,
                   help="GVL_CompTableParam.CORRECTIONS: accept correction tables (reference 'controller') "
                        "instead of motor commands (default: the --table's kind, else the --machine's [table] "
                        "reference, else commands)")
    m.set_defaults(func=cmd_mock_plc)

    pl = sub.add_parser("plc", help="ask the PLC what it runs: status, or verify a table is active")
    psub = pl.add_subparsers(dest="plc_cmd", required=True)
    st = psub.add_parser("status", help="runtime state, interface, active table (version, CRC, machine), last status")
    _target_args(st)
    st.add_argument("--json", action="store_true", help="print the status as one JSON object")
    st.set_defaults(func=cmd_plc_status)
    vf = psub.add_parser("verify", help="exit 0 if exactly TABLE is active on the PLC, 4 if not")
    vf.add_argument("table", metavar="TABLE", help="compensation table, .json or .csv", role="input")
    _target_args(vf)
    vf.add_argument("--json", action="store_true", help="print the verdict as one JSON object")
    vf.set_defaults(func=cmd_plc_verify)
    ul = psub.add_parser("unlock", help="take the PLC's staging area over from a client that is gone and free it "
                                        "(the PLC hands it over only once that client has been silent for its "
                                        "staging lease: a live owner is never broken); asks first, logs to the "
                                        "audit file")
    _target_args(ul)
    ul.add_argument("--yes", action="store_true", help="do not ask for confirmation")
    ul.add_argument("--wait", type=float, default=None, metavar="S",
                    help="seconds to wait for the owner's lease to end (default: the PLC's staging lease, 30 s, "
                         "plus 5 s)")
    ul.add_argument("--audit", default="bridge_audit.log", metavar="FILE", role="output",
                    help="audit log to append to (default: bridge_audit.log in the current folder)")
    ul.set_defaults(func=cmd_plc_unlock)

    lp = sub.add_parser("loop", help="twin in the loop: pointing error before and after a push")
    lp.add_argument("--table", default=None, metavar="TABLE", role="input", kinds=("ocpm_2dof",),
                    help="table to push (default: built from the twin's own error set, see --errors)")
    lp.add_argument("--transport", choices=("ads", "modbus"), default="ads",
                    help="mock PLC transport (default ads)")
    lp.add_argument("--preset", default="paper-table2", kinds=("ocpm_2dof",),
                    help="error set of the virtual machine (default paper-table2)")
    lp.add_argument("--errors", default=None, metavar="PARAMS.json", help="error set of the virtual machine",
                    role="input")
    lp.add_argument("--targets", type=int, default=24, help="number of test orientations (default 24)")
    lp.add_argument("--grid", default="73,31", metavar="NPHI,NTHETA", help="table grid (default 73,31)")
    lp.add_argument("--seed", type=int, default=1, help="random seed of orientations and tracker noise")
    lp.add_argument("--json", default=None, metavar="OUT.json", help="write the result as JSON", role="output",
                    suffixes=(".json",))
    lp.set_defaults(func=cmd_loop)


def _audit_default(args) -> None:
    """The audit log is an output like any other (checked first, its 'wrote' line after): beside TABLE
    unless ``--audit`` or ``--no-audit``."""
    args.audit = None if args.no_audit else (args.audit or str(Path(args.table).with_name("bridge_audit.log")))


def _target_args(p: Command) -> None:
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--ads", default=None, metavar="NETID@HOST[:PORT]", help="TwinCAT ADS target")
    g.add_argument("--modbus", default=None, metavar="HOST[:PORT]", help="Modbus TCP target (TF6250)")
    p.add_argument("--ams-port", type=int, default=851, help="AMS port of the PLC runtime (default 851)")
    p.add_argument("--timeout", type=float, default=2.0, metavar="S", help="per-request time-out (default 2 s)")
    p.add_argument("--local-netid", default=None, metavar="NETID",
                   help="AMS NetID of this client (ADS; default: AdsLib derives it from the local IP + .1.1). "
                        "The PLC needs a route to it (docs/bridge.md, 'Routes')")


def _quiet_libraries() -> None:
    """One clear line per failure: silence AdsLib's and pymodbus' own logging (CLI process only)."""
    from pmcal.bridge.ads import set_adslib_log_level

    set_adslib_log_level(4)
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)


def make_link(args, writes=None):
    """The link named by ``--ads`` / ``--modbus`` (InputError for a malformed target): :func:`pmcal.api.open_link`."""
    from pmcal.api import open_link

    return open_link(args.ads, args.modbus, ams_port=args.ams_port, timeout_s=args.timeout, writes=writes,
                     local_netid=getattr(args, "local_netid", None))


def cmd_push(args) -> int:
    from pmcal.api import push
    from pmcal.bridge.comptable import CompTable
    from pmcal.bridge.errors import BridgeError
    from pmcal.bridge.transfer import PushOptions, check_writable

    if args.attempts < 1:
        raise InputError(f"attempts must be at least 1, got {args.attempts}", field="--attempts")
    if not (args.ack_timeout > 0):
        raise InputError(f"acknowledgement time-out must be positive, got {args.ack_timeout}",
                         field="--ack-timeout")
    if not (args.wait_motion >= 0.0) or args.wait_motion > 3600.0:
        raise InputError(f"wait for motion must be 0..3600 s, got {args.wait_motion}", field="--wait-motion")
    table = CompTable.load(args.table).validate()       # checksums and values: before connecting
    selected = getattr(args, "selected_machine", None)       # a folder's machine goes by its name, not its path
    check_table_for(table, args.table, selected.name if selected is not None else getattr(args, "machine", None),
                    bool(args.force))
    link = make_link(args, writes=frozenset() if args.dry_run else None)
    _quiet_libraries()
    audit = args.audit                                   # _audit_default: None with --no-audit
    # everything that can fail locally, before the first byte goes to the PLC
    if audit is not None and not args.dry_run:
        check_writable(audit, "--audit")
    if args.json:
        check_writable(args.json, "--json", replace=True)
    options = PushOptions(attempts=args.attempts, ack_timeout_s=args.ack_timeout, dry_run=args.dry_run,
                          wait_motion_s=args.wait_motion)
    try:
        rep = push(table, link=link, options=options, audit_path=audit)      # the library's pmcal.push
    except KeyboardInterrupt as exc:        # Ctrl-C, or SIGTERM (pmcal.cli.Terminated): the PLC decides the fate
        how = "terminated" if type(exc).__name__ == "Terminated" else "interrupted"
        flag = f"--{link.transport} {link.target}"
        print(f"pmcal: push of {args.table} v{table.version} {how}: the PLC activates only whole, checked tables, "
              f"so either v{table.version} is active or the previous table still runs; 'pmcal plc status {flag}' "
              f"says which, in words", file=sys.stderr)
        return 143 if how == "terminated" else 130
    except BridgeError as exc:
        print(f"pmcal: failed: push of {args.table} to {link.transport} {link.target}: {exc}", file=sys.stderr)
        _write_json(args.json, getattr(exc, "report", None))
        return exc.exit_status
    _write_json(args.json, rep)
    total_ms = 1000.0 * rep.timings_s.get("total", 0.0)
    sent = f", {rep.bytes_sent} bytes, sha256 {rep.sha256_sent[:16]}" if rep.bytes_sent else ""
    print(f"{rep.result}: {args.table} v{rep.version} -> {link.transport} {link.target}: {rep.message} "
          f"(crc {rep.crc32}{sent}, {total_ms:.1f} ms)")
    return 0


def check_table_for(table, path, machine: str | None, force: bool) -> None:
    """Before any link opens: the table is for ``machine`` (``pmcal --machine``), and was not made with
    ``--force`` from a calibration flagged not usable (its JSON's ``quality``), unless ``force``."""
    from pmcal.campaign_quality import refuse_unusable

    if machine and table.machine != machine:
        raise InputError(f"the table is for machine '{table.machine}', not '{machine}' (pmcal --machine "
                         f"{table.machine} push ... if that is the machine behind the link)", file=str(path),
                         field="machine")
    if Path(path).suffix.lower() == ".json":
        try:
            doc = json.loads(Path(path).read_text(encoding="utf-8-sig"))
        except (OSError, ValueError):
            doc = None                                  # CompTable.load read it: cannot happen
        refuse_unusable(doc, str(path), force)


def plc_status(link) -> dict:
    """What the PLC runs, read over ``link`` (read-only): one dict, JSON-ready."""
    from pmcal.bridge.plc_types import Header

    with link:
        link.check_interface()
        st = link.read_state()
        h = Header.unpack(link.read_active_header())
    name = lambda v: getattr(v, "name", v)  # noqa: E731
    return {"transport": link.transport, "target": link.target, "runtime": "RUN",
            "interface_version": _interface_version(), "active_version": st.active_version,
            "active_crc32": f"0x{st.active_crc:08X}", "machine": h.machine if st.active_version else None,
            "format_version": h.format_version if st.active_version else None,
            "reference": {0: "none", 1: "nominal_ik", 2: "controller"}.get(h.reference, h.reference) if st.active_version else None,
            "grid": list(h.n) if st.active_version else None,
            "motors": h.n_motors if st.active_version else None,
            "last_status": name(st.status), "state": name(st.state), "ack_token": st.ack_token,
            "staging_owner": f"0x{st.staging_owner:08X}" if st.staging_owner else None,
            "plc_cycle": st.cycle,
            "time": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}


def _interface_version() -> int:
    from pmcal.bridge.plc_types import INTERFACE_VERSION

    return INTERFACE_VERSION           # check_interface() refused any other


def _status_link(args):
    from pmcal.bridge.errors import BridgeError  # noqa: F401  (callers catch it)

    return make_link(args, writes=frozenset())


def cmd_plc_status(args) -> int:
    from pmcal.bridge.errors import BridgeError

    link = _status_link(args)
    _quiet_libraries()
    try:
        s = plc_status(link)
    except BridgeError as exc:
        print(f"pmcal: failed: status of {link.transport} {link.target}: {exc}", file=sys.stderr)
        return exc.exit_status
    if args.json:
        print(json.dumps(dict(s, summary=status_words(s))))
    else:
        print(f"{s['transport']} {s['target']}: runtime {s['runtime']}, interface v{s['interface_version']}, "
              f"active table v{s['active_version']} crc {s['active_crc32']} machine {s['machine']} "
              f"(reference {s['reference']}, grid {s['grid']}), last status {s['last_status']}, "
              f"manager {s['state']}, at {s['time']}")
        print(status_words(s))
    return 0


#: the PLC's last status (ST_CompTableState.eStatus) in a user's words: what became of the last commit
_LAST_COMMIT = {
    "NONE": "no commit since the PLC started",
    "OK": "the last commit was checked, activated and saved",
    "OK_NOT_PERSISTED": "the last commit was activated but not saved: a power cut without UPS would bring back "
                        "the previous table (push it again)",
    "BUSY": "a commit is being checked right now (ask again in a second)",
    "PLC_STARTING": "the PLC is re-checking its saved table after a restart (ask again in a few seconds)",
    "WITHDRAWN": "the last commit was withdrawn before the swap (its push stopped, or its lease ended): the table "
                 "it carried is NOT active; push it again",
    "SWAP_TIMEOUT": "the last commit timed out waiting for the machine to stand still: its table is NOT active",
}


def status_words(s: dict) -> str:
    """What :func:`plc_status` found, as sentences a user acts on: which table runs, what became of the last
    commit (a push that was killed: did it land?), whether a client still holds the staging area."""
    if s["active_version"]:
        runs = (f"The PLC runs table v{s['active_version']} (CRC-32 {s['active_crc32']}, machine {s['machine']}): "
                "a push of that version landed; any other did not.")
    else:
        runs = "The PLC runs no table (no compensation applied)."
    last = _LAST_COMMIT.get(s["last_status"], f"the last commit was refused by the PLC's checks ({s['last_status']}): "
                                              "its table is NOT active")
    if s["staging_owner"]:
        held = (f" The staging area is held by client {s['staging_owner']}: a push in progress, or one that was "
                "killed and commits nothing more; the PLC frees it when its lease ends (seconds), 'pmcal plc unlock' "
                "at once.")
    else:
        held = " No push holds the staging area."
    return f"{runs} {last[0].upper()}{last[1:]}.{held}"


def cmd_plc_verify(args) -> int:
    """Exit 0 if exactly TABLE (version, CRC-32 and the whole header) is active, 4 if not."""
    from pmcal.bridge.comptable import CompTable
    from pmcal.bridge.errors import BridgeError
    from pmcal.bridge.plc_types import Header

    table = CompTable.load(args.table).validate()
    link = _status_link(args)
    _quiet_libraries()
    try:
        with link:
            link.check_interface()
            st = link.read_state()
            active = link.read_active_header()
    except BridgeError as exc:
        print(f"pmcal: failed: verify against {link.transport} {link.target}: {exc}", file=sys.stderr)
        return exc.exit_status
    want = Header.of(table)
    same = st.active_version == table.version and st.active_crc == table.crc32() and active == want.pack()
    if same:
        why = "active"
    elif st.active_version != table.version:
        why = f"not active: the PLC runs version {st.active_version}"
    elif st.active_crc != table.crc32():
        why = f"not active: version {table.version} is active with another CRC (0x{st.active_crc:08X})"
    else:
        why = "not active: the active header differs (limits, grid, reference or machine)"
    if args.json:
        print(json.dumps({"table": str(args.table), "version": int(table.version), "crc32": f"0x{table.crc32():08X}",
                          "active": same, "active_version": st.active_version,
                          "active_crc32": f"0x{st.active_crc:08X}", "message": why}))
    else:
        print(f"{args.table} v{table.version} crc 0x{table.crc32():08X}: {why} on {link.transport} {link.target}")
    return 0 if same else 4


def cmd_plc_unlock(args) -> int:
    """Take the staging area over from a client that is gone, then free it.

    Claims the area with a fresh token and waits: the PLC hands it over only when its owner has shown
    no activity for the staging lease while another client claims (FB_CompTableManager), so a live
    owner keeps it and this command fails after ``--wait``. Once granted, the area is released
    (``nStagingClaim := NOT token``). Every write carries this command's own token: it never writes
    on behalf of the owner.
    """
    import datetime as dt

    from pmcal.bridge.errors import BridgeError, StagingBusy
    from pmcal.bridge.plc_types import STAGING_LEASE_S, new_token
    from pmcal.bridge.transfer import append_audit, check_writable, claim_area, release_area

    check_writable(args.audit, "--audit")
    if args.wait is not None and not args.wait >= 0:
        raise InputError(f"must be a number of seconds >= 0, got {args.wait}", field="--wait")
    wait_s = STAGING_LEASE_S + 5.0 if args.wait is None else args.wait
    link = make_link(args, writes=frozenset({"staging_claim", "commit"}))
    _quiet_libraries()
    token = new_token()
    try:
        with link:
            link.check_interface()
            st = link.read_state()
            owner = st.staging_owner
            if owner == 0:
                print(f"{link.transport} {link.target}: the staging area is free; nothing to unlock")
                return 0
            state = getattr(st.state, "name", st.state)
            if not args.yes:
                if not sys.stdin.isatty():
                    raise InputError("confirmation needed: run in a terminal or pass --yes", field="--yes")
                answer = input(f"{link.transport} {link.target}: the staging area belongs to session 0x{owner:08X} "
                               f"(manager {state}); wait up to {wait_s:g} s for its lease to end and free it? "
                               "[y/N] ")
                if answer.strip().lower() not in ("y", "yes"):
                    print("not unlocked")
                    return 1
            try:
                claim_area(link, token, wait_s, 0.005)
                freed = release_area(link, token, 2.0, 0.005)
            except StagingBusy:
                freed = False
    except BridgeError as exc:
        print(f"pmcal: failed: unlock of {link.transport} {link.target}: {exc}", file=sys.stderr)
        return exc.exit_status
    append_audit(args.audit, json.dumps({
        "time": dt.datetime.now(dt.timezone.utc).isoformat(timespec="milliseconds"), "event": "unlock",
        "transport": link.transport, "target": link.target, "owner": f"0x{owner:08X}", "manager_state": state,
        "session": f"0x{token:08X}", "result": "ok" if freed else "failed"}))
    if not freed:
        print(f"pmcal: failed: session 0x{owner:08X} kept the staging area for {wait_s:g} s (it is active, or "
              "its lease is longer): nothing changed", file=sys.stderr)
        return 1
    print(f"unlocked: {link.transport} {link.target}: staging area of session 0x{owner:08X} freed after its "
          f"lease (logged in {args.audit})")
    return 0


def _write_json(path, report) -> None:
    if path and report is not None:
        from dataclasses import asdict

        with atomic_write(path) as fh:
            json.dump(asdict(report), fh, indent=1)
            fh.write("\n")


def _check_port_free(port: int) -> None:
    """A busy ``--port``: one line before the mock starts (the Modbus server would only say that it
    could not listen). 0 (a free port) is always free."""
    import socket

    if port == 0:
        return
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)     # as the servers do: TIME_WAIT is no owner
        try:
            s.bind(("127.0.0.1", port))
        except OSError as exc:
            raise InputError(f"cannot listen on 127.0.0.1:{port}: {exc.strerror} (another program, or another mock "
                             "PLC, uses it: choose another port or 0 for a free one)", field="--port") from None


def cmd_mock_plc(args) -> int:
    from pmcal.bridge.comptable import CompTable
    from pmcal.bridge.simulator.faults import Fault

    if not 0 < args.seconds <= MAX_MOCK_SECONDS:
        raise InputError(f"seconds must be in (0, {MAX_MOCK_SECONDS:g}]", field="--seconds")
    if not 0.1 <= args.cycle_ms <= 1000.0:
        raise InputError("cycle must be 0.1 .. 1000 ms", field="--cycle-ms")
    if not 0 <= args.port < 65536:
        raise InputError(f"port {args.port} outside 0..65535", field="--port")
    _check_port_free(args.port)
    for flag, value in (("--restart-after", args.restart_after), ("--power-cut-after", args.power_cut_after)):
        if value is not None and not 0 < value < args.seconds:
            raise InputError(f"must be in (0, {args.seconds:g}) s, got {value:g}", field=flag)
    if not 0 <= args.restart_s <= 600:
        raise InputError(f"must be in [0, 600] s, got {args.restart_s:g}", field="--restart-s")
    if args.staging_lease is not None and not 0 < args.staging_lease <= 3600:
        raise InputError(f"must be in (0, 3600] s, got {args.staging_lease:g}", field="--staging-lease")
    if args.route and not args.ads:
        raise InputError("routes are an ADS notion; give --ads", field="--route")
    for netid in args.route or ():
        parts = netid.split(".")
        if len(parts) != 6 or not all(p.isdigit() and int(p) <= 255 for p in parts):
            raise InputError(f"AMS NetID must be six numbers 0..255 separated by dots, got '{netid}'",
                             field="--route")
    faults = []
    for text in args.fault:
        try:
            faults.append(Fault.parse(text))
        except ValueError as exc:
            raise InputError(str(exc), field="--fault") from None
    seed = CompTable.load(args.table).validate() if args.table else None
    _quiet_libraries()
    if args.ads:
        from pmcal.bridge.simulator.ads_mock import AdsMockPlc as Mock
    else:
        from pmcal.bridge.simulator.modbus_mock import ModbusMockPlc as Mock
    extra = {"routes": args.route} if args.ads and args.route else {}
    if args.plc_motors is not None and not 0 <= args.plc_motors <= 6:
        raise InputError(f"must be 0..6, got {args.plc_motors}", field="--plc-motors")
    from pmcal.bridge.nominal import REFERENCE_CONTROLLER
    from pmcal.bridge.simulator.plc_runtime import PlcTwin

    # what the mock PLC accepts: the options, else the --table's, else the selected machine's table
    # (a folder with a [table]: its name, motors and kind), else the OCPM's
    name, motors, corrections = "ocpm_2dof", 2, False
    spec = getattr(getattr(args, "selected_machine", None), "spec", None)
    if seed is not None:
        name, motors, corrections = seed.machine, seed.n_motors, seed.reference_code == REFERENCE_CONTROLLER
    elif spec is not None and not spec.legacy and spec.table is not None:
        name, motors, corrections = spec.name, len(spec.motors), spec.table.reference == "controller"
    machine = args.plc_machine if args.plc_machine is not None else name
    if len(machine.encode("ascii", "replace")) > 27:
        raise InputError(f"at most 27 characters (STRING(27)), got '{machine}'", field="--plc-machine")
    twin = PlcTwin(machine=machine, motors=args.plc_motors if args.plc_motors is not None else motors,
                   corrections=args.plc_corrections if args.plc_corrections is not None else corrections)
    mock = Mock(twin, port=args.port, cycle_s=args.cycle_ms / 1000.0, lifetime_s=args.seconds,
                restart_s=args.restart_s, **extra)
    mock.faults.arm(*faults)
    if args.staging_lease is not None:
        mock.set_staging_lease(args.staging_lease)
    mock.twin.motion_idle = not args.motion_busy
    if seed is not None:
        mock.twin.seed(seed)
    try:
        mock.start()
    except OSError as exc:
        raise InputError(f"cannot listen on 127.0.0.1:{args.port}: {exc.strerror}", field="--port") from None
    flag = "--ads" if args.ads else "--modbus"
    print(f"mock PLC ({mock.transport}) at {mock.target} for {args.seconds:g} s; "
          f"try: pmcal push TABLE {flag} {mock.target}", flush=True)
    stop = _stop_on_sigterm()
    now = time.monotonic()
    events = sorted((now + after, name) for name, after in (("restart", args.restart_after),
                                                            ("power cut", args.power_cut_after)) if after is not None)
    try:
        while not mock.expired() and not stop:
            time.sleep(0.05)
            if events and time.monotonic() >= events[0][0]:
                _, name = events.pop(0)
                print(f"mock PLC: {name}, back in {mock.restart_s:g} s", flush=True)
                (mock.power_cut if name == "power cut" else mock.restart)()
                st = mock.twin.state
                print(f"mock PLC running again after the {name}: active version {st.active_version}, "
                      f"start-up check {getattr(st.status, 'name', st.status)}", flush=True)
    except KeyboardInterrupt:
        pass
    finally:
        mock.stop()
    st = mock.twin.state
    status = getattr(st.status, "name", st.status)
    print(f"mock PLC stopped: active version {st.active_version}, last status {status}, "
          f"{mock.faults.fired} fault(s) fired")
    return 0


def _stop_on_sigterm() -> list:
    """A list that becomes non-empty on SIGTERM (main thread only), so the mock stops cleanly."""
    import signal
    import threading

    flag: list = []
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, lambda *_: flag.append(True))
    return flag


def cmd_loop(args) -> int:
    """The machine's twin loop: ocpm_2dof's (:mod:`pmcal.apps.ocpm.plc_loop`), a machine folder's
    (:mod:`pmcal.apps.chain_loop`); planar_2dof has none."""
    from pmcal.commands.routing import dispatch

    return dispatch("loop", args)
