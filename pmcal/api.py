"""The library API of pmcal: read a campaign, calibrate, compensate, push the table to the PLC.

The command line (``pmcal identify | compensate | push ...``) is a thin layer over these functions; they
are re-exported at the top level (``pmcal.identify`` ...). Units: mm and degrees; frames and file
formats in ``docs/formats.md``.

Examples
--------
>>> import pmcal
>>> meas = pmcal.read_measurements("m.csv")                       # doctest: +SKIP
>>> cal = pmcal.identify(meas)                                    # doctest: +SKIP
>>> m = cal.setpoints([0.0, 45.0], [10.0, 30.0])                  # doctest: +SKIP
>>> table = cal.compensation_table(version=7)                     # doctest: +SKIP
>>> table.save("t.json")                                          # doctest: +SKIP
>>> report = pmcal.push(table, ads="127.0.0.1.1.1@127.0.0.1:48898")  # doctest: +SKIP

A machine of one's own is a folder (``docs/ADDING_A_MACHINE.md``): :class:`Machine` holds its validated
``machine.toml``, its commands' defaults and its twin; :mod:`pmcal.chain` runs the job on it:

>>> from pmcal import chain
>>> m = pmcal.Machine.from_folder("my_delta")                     # doctest: +SKIP
>>> meas, truth = chain.campaign(m, 48, seed=3)                   # doctest: +SKIP
>>> res = chain.identify(m, meas)                                 # doctest: +SKIP
>>> commands = chain.compensate(m, res.params, chain.sample_targets(m, 12))  # doctest: +SKIP
"""

from __future__ import annotations

from pathlib import Path

from pmcal.bridge.comptable import CompTable
from pmcal.bridge.link import PlcLink
from pmcal.bridge.transfer import PushOptions, PushReport
from pmcal.bridge.transfer import push as _push
from pmcal.calibration import Calibration, identify
from pmcal.errors import InputError
from pmcal.io_ocpm import read_measurements as _read_measurements
from pmcal.machines import Machine
from pmcal.mechanism.ocpm.data import Measurements

__all__ = ["Calibration", "CompTable", "Machine", "Measurements", "PushReport", "identify", "load_calibration",
           "open_link", "push", "read_measurements"]


def read_measurements(path: str | Path, frame: str = "base") -> Measurements:
    """Read a measurement campaign of the over-constrained PM (CSV, ``docs/formats.md``).

    Parameters
    ----------
    path : str or Path
        UTF-8 CSV with ``pose_id, m1_cmd_deg, m2_cmd_deg, t1_x ... t3_z`` (mm, base frame) and optional
        ``temp_c, time_s, payload_kg, m1_approach, m2_approach``. A blocked target has its three cells
        empty (NaN); a row needs at least two targets.
    frame : {"base", "tracker"}
        Frame of the targets; ``"tracker"`` (the tracker's own frame, ``docs/tracker_frame.md``) skips
        the checks that need the base frame. Pass the same ``frame`` to :func:`identify`.

    Returns
    -------
    Measurements

    Raises
    ------
    pmcal.errors.InputError
        Naming file, row and field of the first bad cell (also implausible units).
    """
    if frame not in ("base", "tracker"):
        raise InputError(f"unknown frame '{frame}' (base or tracker)", field="--frame")
    return _read_measurements(path, frame=frame)


def load_calibration(path: str | Path) -> Calibration:
    """Read a parameters file (``pmcal identify`` output, or :meth:`Calibration.save`)."""
    return Calibration.load(path)


def open_link(ads: str | None = None, modbus: str | None = None, *, ams_port: int | None = None,
              timeout_s: float = 2.0, writes=None, local_netid: str | None = None) -> PlcLink:
    """The link to a PLC: ``ads="NETID@HOST[:PORT]"`` (TwinCAT ADS) or ``modbus="HOST:PORT"``.

    ``writes`` limits the variables the link may write (``frozenset()``: read only; default: what a push
    writes). ``local_netid`` sets this client's AMS NetID (ADS; the PLC needs a route back to it).
    Raises InputError naming ``--ads``/``--modbus``/``--timeout``/``--local-netid`` for a malformed value.
    """
    from pmcal.bridge.plc_types import PUSH_WRITES

    if (ads is None) == (modbus is None):
        raise InputError("give exactly one PLC target: ads='NETID@HOST[:PORT]' or modbus='HOST:PORT'",
                         field="--ads")
    if not (timeout_s > 0):
        raise InputError(f"time-out must be positive, got {timeout_s}", field="--timeout")
    writes = PUSH_WRITES if writes is None else writes
    if ads is not None:
        from pmcal.bridge.ads import AdsLink, set_local_netid
        from pmcal.bridge.ads_map import AdsMap, AdsTarget

        if local_netid:
            try:
                set_local_netid(local_netid)
            except ValueError as exc:
                raise InputError(str(exc), field="--local-netid") from None
        try:
            target = AdsTarget.parse(ads)
        except ValueError as exc:
            raise InputError(str(exc), field="--ads") from None
        amap = AdsMap() if ams_port is None else AdsMap(ams_port=ams_port)
        return AdsLink(target, amap=amap, writes=writes, timeout_s=timeout_s)
    from pmcal.bridge.modbus import ModbusLink, parse_host_port

    try:
        host, port = parse_host_port(modbus)
    except ValueError as exc:
        raise InputError(str(exc), field="--modbus") from None
    return ModbusLink(host, port, writes=writes, timeout_s=timeout_s)


def push(table: CompTable | str | Path, ads: str | None = None, modbus: str | None = None, *,
         ams_port: int | None = None, timeout_s: float = 2.0, options: PushOptions | None = None,
         audit_path: str | Path | None = None) -> PushReport:
    """Send a compensation table to the PLC and make it active (staged, checked, swapped at standstill).

    Parameters
    ----------
    table : CompTable or path
        The table (validated again here) or a table file (.json or .csv).
    ads, modbus : str
        Exactly one target: ``"NETID@HOST[:PORT]"`` for TwinCAT ADS, ``"HOST:PORT"`` for Modbus TCP.
    ams_port : int, optional
        AMS port of the PLC runtime (default 851).
    timeout_s : float
        Time-out of one request, s.
    options : PushOptions, optional
        Attempts, acknowledgement time-out, dry run.
    audit_path : path, optional
        Audit log to append one line to (none by default from the API).

    Returns
    -------
    PushReport

    Raises
    ------
    pmcal.errors.InputError
        A bad or stale table, a malformed target (nothing written).
    pmcal.bridge.errors.BridgeError
        The transfer failed; ``exc.report`` says how far it got. The PLC keeps a whole table.
    """
    if (ads is None) == (modbus is None):
        raise InputError("give exactly one PLC target: ads='NETID@HOST[:PORT]' or modbus='HOST:PORT'",
                         field="--ads")
    if not isinstance(table, CompTable):
        table = CompTable.load(table)
    table = table.validate()
    opts = options or PushOptions()
    link = open_link(ads, modbus, ams_port=ams_port, timeout_s=timeout_s,
                     writes=frozenset() if opts.dry_run else None)
    return _push(link, table, opts, audit_path=audit_path)
