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
``machine.toml``, its commands' defaults and its twin. The same lines serve it (the campaign knows its
machine; the calibration is a :class:`~pmcal.chain_calibration.ChainCalibration`):

>>> m = pmcal.Machine.from_folder("my_delta")                     # doctest: +SKIP
>>> meas = pmcal.read_measurements("m.csv", m)                    # doctest: +SKIP
>>> cal = pmcal.identify(meas)                                    # doctest: +SKIP
>>> m_cmd = cal.setpoints([[0.0, 0.0, -800.0]])                   # doctest: +SKIP
>>> table = cal.compensation_table(version=7)                     # doctest: +SKIP

:mod:`pmcal.chain` has the steps one by one (virtual campaign, plan, identification, compensation).
"""

from __future__ import annotations

from pathlib import Path

from pmcal.bridge.comptable import CompTable
from pmcal.bridge.link import PlcLink
from pmcal.bridge.transfer import PushOptions, PushReport
from pmcal.bridge.transfer import push as _push
from pmcal.ocpm.calibration import Calibration
from pmcal.ocpm.calibration import identify as _identify_ocpm
from pmcal.chain_calibration import ChainCalibration
from pmcal.errors import InputError
from pmcal.io_chain import ChainMeasurements
from pmcal.io_chain import read_measurements as _read_chain
from pmcal.ocpm.io import read_measurements as _read_measurements
from pmcal.planar.io import PlanarMeasurements
from pmcal.planar.io import read_measurements as _read_planar
from pmcal.machines import Machine
from pmcal.mechanism.ocpm.data import Measurements
from pmcal.planar.calibration import PlanarCalibration
from pmcal.planar.calibration import identify as _identify_planar
from pmcal.twin.planar.config import default_machine as _planar_machine

__all__ = ["Calibration", "ChainCalibration", "ChainMeasurements", "CompTable", "Machine", "Measurements",
           "PlanarCalibration", "PlanarMeasurements", "PushReport", "identify", "load_calibration", "open_link",
           "push", "read_measurements"]

#: the seeded machine the ocpm-only calls (no machine given) stand for
DEFAULT_MACHINE = "ocpm_2dof"
PLANAR = "planar_2dof"
_FRAMES = ("base", "tracker")


def _machine(machine) -> Machine:
    """A :class:`Machine`, a built-in name or a folder -> Machine (InputError naming ``machine``)."""
    if isinstance(machine, Machine):
        return machine
    return Machine.resolve(DEFAULT_MACHINE if machine is None else machine)


def read_measurements(path: str | Path, machine=None, frame: str = "base"):
    """Read a measurement campaign (CSV, ``docs/formats.md``) of a machine; the campaign knows its machine.

    Parameters
    ----------
    path : str or Path
        UTF-8 CSV. ocpm_2dof: ``pose_id, m1_cmd_deg, m2_cmd_deg, t1_x ... t3_z`` (mm, base frame) and
        optional ``temp_c, time_s, payload_kg, m1_approach, m2_approach``. A machine folder: ``pose_id``,
        one command column per motor (``m1_cmd_deg`` or ``m1_cmd_mm``), ``t1_x ...`` per tracker nest (mm,
        base frame) or ``reading_mm``; optional ``time_s, temp_c``. A blocked target has its three cells
        empty (NaN).
    machine : Machine, str or None
        The machine (:class:`Machine`), a built-in name or a machine folder; None: ocpm_2dof. planar_2dof:
        ``pose_id, theta1_cmd_deg, theta2_cmd_deg, scale_change_mm`` (docs/planar_measurement_format.md).
    frame : {"base", "tracker"}
        ocpm_2dof only: frame of the targets; ``"tracker"`` (the tracker's own frame,
        ``docs/tracker_frame.md``) skips the checks that need the base frame. Pass the same ``frame`` to
        :func:`identify`. (Given as the second positional argument, as before machines, it still works.)

    Returns
    -------
    Measurements (ocpm_2dof), PlanarMeasurements (planar_2dof) or ChainMeasurements (a machine folder);
    ``.machine`` is its machine (planar_2dof and folders)

    Raises
    ------
    pmcal.errors.InputError
        Naming file, row and field of the first bad cell (also implausible units).
    """
    if isinstance(machine, str) and machine in _FRAMES:      # read_measurements(path, "tracker")
        machine, frame = None, machine
    if frame not in _FRAMES:
        raise InputError(f"unknown frame '{frame}' (base or tracker)", field="--frame")
    m = _machine(machine)
    if m.legacy and m.spec.kind == DEFAULT_MACHINE:
        return _read_measurements(path, frame=frame)
    if frame != "base":
        raise InputError(f"frame='tracker' is for ocpm_2dof; {m.name}'s campaign is in its base frame",
                         field="--frame")
    meas = _read_planar(path, _planar_machine().geometry) if m.legacy else _read_chain(path, m.spec)
    meas.machine = m
    return meas


def identify(meas, **options):
    """Identify the machine's errors from a campaign read by :func:`read_measurements`.

    Parameters
    ----------
    meas : Measurements, PlanarMeasurements or ChainMeasurements
        The campaign (it knows its machine).
    **options
        ocpm_2dof: those of :func:`pmcal.ocpm.calibration.identify` (``model="full"|"paper"``, ``method``,
        ``sigma``, ``seed`` ...). planar_2dof: those of :func:`pmcal.planar.calibration.identify` (``model``,
        ``method``, ``sigma``, ``allow_rank_deficient``). A machine folder: ``sigma_mm`` (tracker noise, mm;
        default machine.toml's).

    Returns
    -------
    Calibration (ocpm_2dof), PlanarCalibration (planar_2dof) or ChainCalibration (a machine folder):
    ``setpoints``, ``compensation_table``, ``save``, the parameters document.

    Raises
    ------
    pmcal.errors.InputError
        An option the machine does not have, too few or implausible poses.
    """
    if isinstance(meas, ChainMeasurements):
        if meas.machine is None:
            raise InputError("this campaign does not know its machine: read it with "
                             "pmcal.read_measurements(path, machine)", field="machine")
        unknown = sorted(set(options) - {"sigma_mm"})
        if unknown:
            raise InputError(f"option {unknown[0]!r} is not one of a machine folder's (sigma_mm)", field=unknown[0])
        return ChainCalibration.identify(meas.machine, meas, options.get("sigma_mm"))
    if isinstance(meas, PlanarMeasurements):
        return _identify_planar(meas, **options)
    return _identify_ocpm(meas, **options)


def load_calibration(path: str | Path, machine=None):
    """Read a parameters file (``pmcal identify`` output, or ``cal.save``) of ``machine`` (a
    :class:`Machine`, a built-in name or a folder; None: ocpm_2dof)."""
    m = _machine(machine)
    if not m.legacy:
        return ChainCalibration.load(path, m)
    if m.spec.kind == PLANAR:
        return PlanarCalibration.load(path)
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
         link: PlcLink | None = None, ams_port: int | None = None, timeout_s: float = 2.0,
         options: PushOptions | None = None, audit_path: str | Path | None = None) -> PushReport:
    """Send a compensation table to the PLC and make it active (staged, checked, swapped at standstill).

    Parameters
    ----------
    table : CompTable or path
        The table (validated again here) or a table file (.json or .csv).
    ads, modbus : str
        Exactly one target: ``"NETID@HOST[:PORT]"`` for TwinCAT ADS, ``"HOST:PORT"`` for Modbus TCP.
    link : PlcLink, optional
        Instead of a target: a link already made by :func:`open_link` (with the writes of a push, or none
        for a dry run); the command line makes its link first to name it in its messages.
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
    if (ads is None) + (modbus is None) + (link is None) != 2:
        raise InputError("give exactly one PLC target: ads='NETID@HOST[:PORT]', modbus='HOST:PORT' or link=",
                         field="--ads")
    if not isinstance(table, CompTable):
        table = CompTable.load(table)
    table = table.validate()
    opts = options or PushOptions()
    if link is None:
        link = open_link(ads, modbus, ams_port=ams_port, timeout_s=timeout_s,
                         writes=frozenset() if opts.dry_run else None)
    return _push(link, table, opts, audit_path=audit_path)
