"""Persistence and restore (issue 12, Deliver 2): the mock PLCs model a power cycle; the active table,
its header and the version order survive it, staging does not, and a damaged persistent table is
dropped at start-up rather than used. Lookups go through a plain link after the restart."""

from __future__ import annotations

import time

import numpy as np
import pytest

from pmcal.bridge.simulator.ads_mock import AdsMockPlc
from pmcal.bridge.simulator.modbus_mock import ModbusMockPlc
from pmcal.bridge.plc_types import LOOKUP_WRITES, LookupResult, Status
from pmcal.bridge.transfer import PushOptions, push
from pmcal.errors import InputError
from tests.bridge_fixtures import ads_link, make_table, modbus_link, running

MOCKS = [(AdsMockPlc, ads_link), (ModbusMockPlc, modbus_link)]


@pytest.mark.parametrize("mock, link", MOCKS, ids=["ads", "modbus"])
def test_restart_after_a_push_keeps_the_table_and_refuses_a_stale_one(mock, link):
    table = make_table(version=7, offset_deg=0.2)
    with running(mock(lifetime_s=60.0)) as plc:
        assert push(link(plc), table).result == "ok"
        before = link(plc, writes=LOOKUP_WRITES)
        with before:
            want = before.lookup(123.0, 33.0)
        plc.restart()
        assert plc.twin.wait_started()                   # the manager re-checks the table over some cycles
        st = plc.twin.state
        assert (st.active_version, st.active_crc, st.status) == (7, table.crc32(), Status.OK)
        assert plc.twin.active_table()[1].tobytes() == table.values.tobytes()
        with link(plc, writes=LOOKUP_WRITES) as after:
            got = after.lookup(123.0, 33.0)
        assert (got.result, got.table_version, got.m1_deg, got.m2_deg) == (LookupResult.OK, 7, want.m1_deg,
                                                                            want.m2_deg)
        # the version order survived: an older table is refused (by the bridge, before writing) ...
        with pytest.raises(InputError, match="not newer"):
            push(link(plc), make_table(version=6))
        # ... and by the PLC itself when staged directly
        stale = make_table(version=6)
        from pmcal.bridge.plc_types import Header, shadow_rows
        with plc.twin.lock:
            plc.twin.write_shadow_bytes(0, shadow_rows(stale))

        def put(key: str, data: bytes) -> None:
            if plc.transport == "modbus":       # the ST copies these from the %M area every cycle
                off = plc.rmap.offset(key)
                plc.area.image[off:off + len(data) // 2] = np.frombuffer(data, dtype="<u2")
            else:
                plc.twin.write_symbol(key, data)

        with plc.twin.lock:
            put("shadow_header", Header.of(stale).pack())
            put("staging_claim", (0x80000077).to_bytes(4, "little"))
        time.sleep(0.05)                                  # the claim is granted
        with plc.twin.lock:
            put("commit", (0x80000077).to_bytes(4, "little"))
        time.sleep(0.05)
        assert (plc.twin.state.status, plc.twin.state.active_version) == (Status.STALE_VERSION, 7)


@pytest.mark.parametrize("mock, link", MOCKS, ids=["ads", "modbus"])
def test_restart_mid_life_loses_staging_only(mock, link):
    good, new = make_table(version=1), make_table(version=2, offset_deg=0.3)
    with running(mock(lifetime_s=60.0)) as plc:
        plc.twin.seed(good)
        plc.twin.motion_idle = False                     # the commit waits for motion ...
        from pmcal.bridge.errors import BridgeError
        with pytest.raises(BridgeError):
            push(link(plc), new, PushOptions(ack_timeout_s=0.2))
        plc.restart()                                    # ... and the PLC restarts meanwhile
        assert plc.twin.wait_started()
        st = plc.twin.state
        assert (st.active_version, st.staging_owner, plc.twin.commit_token) == (1, 0, 0)
        assert plc.twin.active_table()[1].tobytes() == good.values.tobytes()
        plc.twin.motion_idle = True
        assert push(link(plc), new).result == "ok"       # a fresh push after the restart works
        assert plc.twin.active_table()[1].tobytes() == new.values.tobytes()


def test_damaged_persistent_table_is_dropped_at_start_up():
    with running(AdsMockPlc(lifetime_s=60.0)) as plc:
        plc.twin.seed(make_table(version=3))
        plc.twin.corrupt_persistent()
        plc.restart()
        plc.twin.wait_started()
        st = plc.twin.state
        assert (st.active_version, st.status) == (0, Status.CRC_MISMATCH)
        with ads_link(plc, writes=LOOKUP_WRITES) as link:
            assert link.lookup(10.0, 10.0).result == LookupResult.NO_TABLE
        assert push(ads_link(plc), make_table(version=4)).result == "ok"
