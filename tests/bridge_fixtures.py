"""Shared set-up of the bridge tests: realistic tables and mock PLCs on loopback ephemeral ports.

Tables come from the nominal inverse kinematics of the over-constrained PM (calib.ocpm.kinematics),
deg in and out. Every mock runs on 127.0.0.1 with a port the OS picks and its own AMS NetID, so the
tests run in parallel (pytest -n) without sharing anything.
"""

from __future__ import annotations

import logging
import threading
import time
from contextlib import contextmanager

import numpy as np
import pytest

from pmcal.bridge.comptable import Axis, CompTable, Motor
from pmcal.bridge.simulator.plc_runtime.cost_model import TASK_SHARE
from pmcal.mechanism.ocpm.kinematics import nominal_ik

MOTOR_LIMITS_DEG = (-120.0, 60.0)
MAX_STEP_DEG = 12.0
#: short client time-outs so that time-out faults cost little (requests on loopback take < 1 ms)
TIMEOUT_S = 0.25
#: client and acknowledgement time-outs (s) for 100 x 100 tables: the interpreted ST (plc/, run by
#: bridge.plc_runtime) checks ~80 000 nominal-IK commands over ~100 task cycles, ~1 s of CPU here and
#: more on a loaded machine, and a task cycle holds the PLC memory (as ADS sees it) for up to ~30 ms
BIG_TABLE_TIMEOUT_S = 2.0
BIG_TABLE_ACK_S = 30.0

logging.getLogger("pymodbus").setLevel(logging.CRITICAL)


def nominal_setpoints(phi_deg: np.ndarray, theta_deg: np.ndarray) -> np.ndarray:
    """Motor commands (deg) of the nominal machine at (phi, theta) in deg."""
    return np.rad2deg(nominal_ik(np.deg2rad(phi_deg), np.deg2rad(theta_deg)))


def make_table(version: int = 1, n_phi: int = 37, n_theta: int = 13, offset_deg: float = 0.0,
               reference="nominal_ik") -> CompTable:
    """A valid table from the nominal IK (plus ``offset_deg`` on both motors, to tell tables apart).

    ``reference=None`` stores absolute commands (format version 1 scheme).
    """
    return CompTable.from_setpoints(lambda p, t: nominal_setpoints(p, t) + offset_deg, machine="ocpm_2dof",
                                    version=version, n_phi=n_phi, n_theta=n_theta,
                                    motor_limits_deg=MOTOR_LIMITS_DEG, max_step_deg=MAX_STEP_DEG,
                                    reference=reference)


def delta_correction_table(version: int, offset: float) -> CompTable:
    """A Delta-shaped table: 13 x 13 x 9 nodes over x, y, z (mm), 3 revolute motors, corrections to the
    controller's IK (nReference 2) of at most 0.3 deg, as mjcf/delta_3dof's default [table]."""
    axes = [Axis("x", "mm", -150.0, 150.0, 13), Axis("y", "mm", -150.0, 150.0, 13), Axis("z", "mm", -900.0, -700.0, 9)]
    motors = [Motor(f"m{k + 1}", "deg", -1.0, 1.0, 0.5) for k in range(3)]
    shape = (13, 13, 9, 3)
    x = CompTable(machine="delta_3dof", version=1, axes=axes, motors=motors, values=np.zeros(shape)).nodes()
    values = 0.2 * np.sin(x / 80.0) + offset
    return CompTable(machine="delta_3dof", version=version, axes=axes, motors=motors, values=values,
                     reference="controller").validate()


@contextmanager
def running(mock):
    """Start a mock PLC, yield it, always stop it."""
    mock.start()
    try:
        yield mock
    finally:
        mock.stop()


def ads_link(mock, **kwargs):
    from pmcal.bridge.ads import AdsLink

    return AdsLink(mock.address, timeout_s=kwargs.pop("timeout_s", TIMEOUT_S), **kwargs)


def modbus_link(mock, **kwargs):
    from pmcal.bridge.modbus import ModbusLink

    return ModbusLink(mock.host, mock.port, rmap=mock.rmap, timeout_s=kwargs.pop("timeout_s", TIMEOUT_S),
                      **kwargs)


@pytest.fixture
def ads_plc():
    from pmcal.bridge.ads import set_adslib_log_level
    from pmcal.bridge.simulator.ads_mock import AdsMockPlc

    set_adslib_log_level(4)
    with running(AdsMockPlc(lifetime_s=120.0)) as plc:
        yield plc


@pytest.fixture
def modbus_plc():
    from pmcal.bridge.simulator.modbus_mock import ModbusMockPlc

    with running(ModbusMockPlc(lifetime_s=120.0)) as plc:
        yield plc


#: repository root (for subprocesses running ``python -m pmcal.cli``)
ROOT_DIR = str(__import__("pathlib").Path(__file__).resolve().parent.parent)


def during_restart(plc, probe, limit: int = 400) -> list:
    """Restart ``plc`` (taking its ``restart_s``) in a thread and collect what ``probe()`` returns,
    every 20 ms, until the PLC runs again; ``probe`` returns None when it could not connect."""
    down = threading.Thread(target=plc.restart)
    down.start()
    time.sleep(0.05)
    seen = []
    while down.is_alive() and len(seen) < limit:
        got = probe()
        if got is not None:
            seen.append(got)
        time.sleep(0.02)
    down.join()
    return seen


def ads_state_code(netid: str, ams_port: int, plc, timeout_ms: int = 500) -> int | None:
    """A plain pyads ``read_state`` against ``plc``: 0, the ADS error code, or None if nothing listens."""
    import pyads

    conn = pyads.Connection(netid, ams_port, f"{plc.host}:{plc.port}")
    try:
        conn.open()
    except pyads.ADSError:
        return None
    try:
        conn.set_timeout(timeout_ms)
        conn.read_state()
        return 0
    except pyads.ADSError as exc:
        return exc.err_code
    finally:
        conn.close()


#: bytes every task cycle copies besides the budgeted work: the interface structs (headers, state, lookup)
#: the manager, the lookup and the Modbus mapping assign each cycle (format 4: 248-byte headers and 96 bytes of
#: lookup structs; the busiest Modbus cycle copies 864 bytes besides the budget)
INTERFACE_COPIES = 1024


def assert_within_cycle_budget(plc) -> None:
    """The busiest task cycle of the interpreted ST stayed within GVL_CompTableParam's budget: at most
    BUDGET_IK_PER_CYCLE nominal IKs and BUDGET_BYTES_PER_CYCLE bytes moved (plus the interface copies)."""
    rt = plc.twin.runtime
    ik, nbytes = rt.constant("GVL_CompTableParam.BUDGET_IK_PER_CYCLE"), rt.constant("GVL_CompTableParam.BUDGET_BYTES_PER_CYCLE")
    assert rt.calls_max.get("F_CompTableNominalIk", 0) <= ik, rt.calls_max
    assert rt.work_max["bytes_copied"] <= nbytes + INTERFACE_COPIES, rt.work_max
    assert rt.task_us_max <= TASK_SHARE * 1e6 * rt.cycle_s, (rt.task_us_max, rt.work_max)


def commit_on_twin(plc, table: CompTable, token: int = 0x800D0001):
    """Stage and commit ``table`` on a PlcTwin cycle by cycle (no task thread, no transport): claim,
    stage, commit, run cycles until the PLC acknowledges ``token`` idle (or stops). Returns the final
    state and the task's modelled time of every cycle of the commit (µs, cost_model)."""
    from pmcal.bridge import plc_types
    from pmcal.bridge.plc_types import Header, State, shadow_rows

    rows = shadow_rows(table)
    plc.write_symbol("staging_claim", token.to_bytes(4, "little"))
    plc.cycle()                                            # the claim is granted
    plc.write_symbol("shadow_header", Header.of(table).pack())
    plc.write_symbol("shadow", rows + bytes(plc_types.SHADOW_SIZE - len(rows)))
    plc.runtime.reset_work_max()
    plc.write_symbol("commit", token.to_bytes(4, "little"))
    micros = []
    while True:
        plc.cycle()
        micros.append(plc.runtime.task_us_last)
        st = plc.state
        if plc.stopped or (st.ack_token == token and st.state == State.IDLE):
            return st, micros
        if len(micros) == 1 and st.state != State.CHECKING:
            return st, micros


def wait_state(plc, ready, timeout_s: float = 20.0):
    """The PLC's state once ``ready(state)`` (read from the twin, the task running), else AssertionError."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        st = plc.twin.state
        if ready(st):
            return st
        time.sleep(0.005)
    raise AssertionError(f"PLC state never got there: {plc.twin.state}")


def raw_commit(plc, ln, header: bytes, rows: bytes, token: int):
    """A client without any of the bridge's table checks: claim with ``token``, stage ``header`` and
    ``rows`` through the transport, commit and return the PLC's answer (the state with nAckToken = token),
    then clear the answer and release. Only the PLC judges the table."""
    from pmcal.bridge.plc_types import State, done_value

    ln.write_claim(token)
    wait_state(plc, lambda s: s.staging_owner == token)
    ln.stage(header, rows)
    ln.write_commit(token)
    st = wait_state(plc, lambda s: s.ack_token == token and s.state in (State.IDLE, State.STARTING))
    ln.write_commit(done_value(token))
    ln.write_claim(done_value(token))
    wait_state(plc, lambda s: s.staging_owner != token)
    return st
