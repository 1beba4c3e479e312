"""Fault injection on both transports: the active table survives, the bridge says why, a rerun works.

Every fault kind fires on every request at one point of the transfer (persistent fault), with the
last good table active on the PLC. The push must fail with one clear line, leave the last good table
active, and succeed once the fault is gone. Faults at the acknowledgement run while the machine
moves, so the commit is still pending when the link fails (the bridge must withdraw it).
"""

from __future__ import annotations

from dataclasses import replace

import pytest

from pmcal.bridge.simulator.ads_mock import AdsMockPlc
from pmcal.bridge.errors import BridgeError, DeviceError, InterfaceError, LinkError, Rejected
from pmcal.bridge.simulator.faults import Fault, Kind, Point
from pmcal.bridge.simulator.modbus_mock import ModbusMockPlc
from pmcal.bridge.plc_types import Status
from pmcal.bridge.transfer import PushOptions, push
from tests.bridge_fixtures import TIMEOUT_S, ads_link, make_table, modbus_link, running

OPTIONS = PushOptions(attempts=2, ack_timeout_s=0.3, idle_timeout_s=0.5, retry_pause_s=0.01)
#: for pushes that must reach the PLC's verdict: FB_CompTableCheck spreads its work over ~40 task cycles
#: (4 table rows per cycle), and the interpreted ST may run slower than real time on a loaded machine
VERDICT = replace(OPTIONS, ack_timeout_s=5.0)
POINTS = [Point.BEFORE_STAGE, Point.MID_STAGE, Point.AFTER_STAGE, Point.ACK_WAIT]
KINDS = [Kind.DELAY, Kind.NO_REPLY, Kind.DROP, Kind.CORRUPT, Kind.ERROR]


def _mock(transport: str):
    mock = AdsMockPlc if transport == "ads" else ModbusMockPlc
    return running(mock(lifetime_s=60.0))


def _link(transport: str, plc):
    return (ads_link if transport == "ads" else modbus_link)(plc)


def _expected(kind: Kind, point: Point) -> type[BridgeError]:
    if kind == Kind.ERROR:
        return DeviceError
    if kind == Kind.CORRUPT:
        return {Point.BEFORE_STAGE: InterfaceError, Point.ACK_WAIT: BridgeError}.get(point, LinkError)
    return LinkError


@pytest.mark.parametrize("transport", ["ads", "modbus"])
@pytest.mark.parametrize("point", POINTS, ids=lambda p: p.value)
@pytest.mark.parametrize("kind", KINDS, ids=lambda k: k.value)
def test_fault_keeps_last_good_table_and_rerun_succeeds(transport, point, kind):
    good, new = make_table(version=1), make_table(version=2, offset_deg=0.25)
    with _mock(transport) as plc:
        plc.twin.seed(good)
        plc.faults.arm(Fault(kind, point, delay_s=3 * TIMEOUT_S if kind == Kind.DELAY else None))
        plc.twin.motion_idle = point != Point.ACK_WAIT
        with pytest.raises(_expected(kind, point)) as exc:
            push(_link(transport, plc), new, OPTIONS)
        assert plc.faults.fired >= 1
        message = str(exc.value)
        assert "\n" not in message and ("active version stays 1" in message or "nothing committed" in message)
        assert exc.value.report.result == "failed" and exc.value.report.version == 2
        st = plc.twin.state
        assert (st.active_version, st.active_crc) == (1, good.crc32())
        assert plc.twin.active_table()[1].tobytes() == good.values.tobytes()

        plc.faults.clear()
        plc.twin.motion_idle = True
        rep = push(_link(transport, plc), new, VERDICT)
        assert (rep.result, rep.active_version) == ("ok", 2)
        assert plc.twin.active_table()[1].tobytes() == new.values.tobytes()


@pytest.mark.parametrize("transport", ["ads", "modbus"])
def test_table_damaged_in_plc_memory_is_rejected_by_the_plc_crc(transport):
    good, new = make_table(version=1), make_table(version=2, offset_deg=0.25)
    with _mock(transport) as plc:
        plc.twin.seed(good)
        plc.faults.arm(Fault(Kind.CORRUPT, Point.COMMIT, times=1))
        with pytest.raises(Rejected, match="CRC_MISMATCH") as exc:
            push(_link(transport, plc), new, VERDICT)
        assert exc.value.exit_status == 3 and exc.value.report.attempts == 1      # never retried
        assert (plc.twin.state.status, plc.twin.state.active_version) == (Status.CRC_MISMATCH, 1)
        assert push(_link(transport, plc), new, VERDICT).active_version == 2


@pytest.mark.parametrize("transport", ["ads", "modbus"])
def test_lost_commit_is_retried_then_reported(transport):
    good, new = make_table(version=1), make_table(version=2, offset_deg=0.25)
    with _mock(transport) as plc:
        plc.twin.seed(good)
        plc.faults.arm(Fault(Kind.DROP, Point.COMMIT))
        with pytest.raises(LinkError, match="gave up after 2 attempts.*active version stays 1"):
            push(_link(transport, plc), new, OPTIONS)
        assert plc.faults.fired == 2 and plc.twin.state.active_version == 1
        plc.faults.clear()
        plc.faults.arm(Fault(Kind.DROP, Point.COMMIT, times=1))      # one loss: the retry gets it through
        rep = push(_link(transport, plc), new, VERDICT)
        assert (rep.result, rep.attempts, rep.active_version) == ("ok", 2, 2)


@pytest.mark.parametrize("transport", ["ads", "modbus"])
def test_ack_lost_after_the_swap_is_not_committed_twice(transport):
    new = make_table(version=1)
    with _mock(transport) as plc:
        # the ack read is lost after the PLC had 1 s (the check takes ~40 task cycles) to check and swap
        plc.faults.arm(Fault(Kind.DROP, Point.ACK_WAIT, times=1, delay_s=1.0))
        rep = push(_link(transport, plc), new, VERDICT)
        assert (rep.result, rep.attempts, rep.active_version) == ("already_active", 2, 1)
        assert plc.twin.active_table()[1].tobytes() == new.values.tobytes()
