"""Every owner write is fenced (interface 5): claim, commit, withdrawal and release carry the owner's token
(the token, or its complement NOT token), and the PLC compares them with the current owner only. A client
frozen past its lease that resumes and writes (its late release, withdrawal, commit, or the old protocol's
0) changes nothing, on ADS (plain pyads) and Modbus (the transport's primitives); of two pushes at once
every "ok" is true: the later names the earlier as the table it replaced, or one is refused.
"""

from __future__ import annotations

import threading
import time

import pytest

from pmcal.bridge.errors import BridgeError
from pmcal.bridge.simulator.plc_runtime import PlcTwin
from pmcal.bridge.plc_types import Header, State, Status, done_value, shadow_rows
from pmcal.bridge.transfer import PushOptions, push
from pmcal.errors import InputError
from tests.bridge_fixtures import ads_link, make_table, modbus_link, running, wait_state
from tests.test_plc_kind import PlainAds

LEASE_S = 1.0
FORMER, NEW = 0x8F0F0001, 0x8E0E0002


def _mock(transport: str):
    from pmcal.bridge.simulator.ads_mock import AdsMockPlc
    from pmcal.bridge.simulator.modbus_mock import ModbusMockPlc

    twin = PlcTwin(staging_lease_s=LEASE_S, commit_timeout_s=20.0)
    return (AdsMockPlc if transport == "ads" else ModbusMockPlc)(twin, lifetime_s=120.0)


def _client(plc, transport: str):
    return PlainAds(plc) if transport == "ads" else modbus_link(plc)


@pytest.mark.parametrize("transport", ["ads", "modbus"])
def test_a_client_frozen_past_its_lease_changes_nothing_when_it_resumes(transport):
    with running(_mock(transport)) as plc:
        plc.twin.seed(make_table(version=1))
        stale, new = make_table(version=2, offset_deg=0.1), make_table(version=3, offset_deg=0.2)
        with _client(plc, transport) as former, _client(plc, transport) as other:
            former.write_claim(FORMER)                    # the former owner claims, stages, then freezes
            wait_state(plc, lambda s: s.staging_owner == FORMER)
            former.stage(Header.of(stale).pack(), shadow_rows(stale))
            t0 = time.monotonic()
            other.write_claim(NEW)                        # another client claims: granted after the lease
            wait_state(plc, lambda s: s.staging_owner == NEW)
            assert time.monotonic() - t0 >= 0.9 * LEASE_S
            plc.twin.motion_idle = False                  # the new owner's commit waits for the machine
            other.stage(Header.of(new).pack(), shadow_rows(new))
            other.write_commit(NEW)
            wait_state(plc, lambda s: s.state == State.WAIT_MOTION)
            # the former owner resumes: withdrawal (NOT token, and the old protocol's 0), release, commit
            for write, value in ((former.write_commit, done_value(FORMER)), (former.write_commit, 0),
                                 (former.write_claim, done_value(FORMER)), (former.write_claim, 0),
                                 (former.write_commit, FORMER)):
                write(value)
                time.sleep(0.05)                          # ~50 task cycles
                st = plc.twin.state
                assert (st.state, st.staging_owner, st.active_version, st.ack_token) == \
                    (State.WAIT_MOTION, NEW, 1, 0), (hex(value), st)
            plc.twin.motion_idle = True                   # the new owner's commit goes through
            st = wait_state(plc, lambda s: s.ack_token == NEW)
            assert (st.status, st.active_version, st.active_crc) == (Status.OK, 3, new.crc32())
            # after the acknowledgement: the former owner's late clear and release change nothing either
            for write, value in ((former.write_commit, done_value(FORMER)), (former.write_claim, done_value(FORMER))):
                write(value)
                time.sleep(0.05)
                st = plc.twin.state
                assert (st.staging_owner, st.ack_token, st.active_version) == (NEW, NEW, 3), st
            # the owner's own complement clears and releases
            other.write_commit(done_value(NEW))
            other.write_claim(done_value(NEW))
            st = wait_state(plc, lambda s: s.staging_owner == 0)
            assert (st.ack_token, st.active_version) == (0, 3)


@pytest.mark.parametrize("transport", ["ads", "modbus"])
def test_of_two_pushes_at_once_every_ok_is_true(transport):
    link = ads_link if transport == "ads" else modbus_link
    with running(_mock(transport)) as plc:
        plc.twin.seed(make_table(version=1))
        before = 1
        for first, second in ((100, 101), (201, 200)):
            reports, errors, done = {}, {}, []

            def run(version: int) -> None:
                try:
                    reports[version] = push(link(plc), make_table(version=version, offset_deg=version * 1e-3),
                                            PushOptions(claim_timeout_s=LEASE_S + 5.0))
                except (InputError, BridgeError) as exc:
                    errors[version] = exc
                done.append(version)

            threads = [threading.Thread(target=run, args=(v,)) for v in (first, second)]
            for t in threads:
                t.start()
            for t in threads:
                t.join()
            oks = [v for v in done if v in reports and reports[v].result == "ok"]
            assert oks and len(oks) + len(errors) == 2, (reports, errors)
            for v in errors:                               # refused: not newer than the table the other made active
                assert "not newer" in str(errors[v]) and v < max(oks), errors
            assert reports[oks[0]].previous_version == before, reports   # the first ok replaced what was active
            if len(oks) == 2:                              # both ok: the later replaced the earlier
                assert reports[oks[1]].previous_version == oks[0] and oks[1] > oks[0], reports
            assert plc.twin.state.active_version == oks[-1]
            before = oks[-1]


@pytest.mark.parametrize("paging", [True, False], ids=["staging", "silent"])
def test_modbus_page_requests_keep_the_owners_lease(paging):
    """Over Modbus the staging shows as page requests: an owner paging a table in while another client
    claims keeps the area past the lease (activity); a silent owner loses it after the lease."""
    from pmcal.bridge.modbus_map import ModbusMap

    rmap = ModbusMap()
    twin = PlcTwin(staging_lease_s=0.2)
    twin.use_modbus = True
    regs = twin.modbus_memory(rmap.WINDOW)

    def put(at: int, value: int, words: int = 2) -> None:
        for k in range(words):
            regs[at + k] = (value >> (16 * k)) & 0xFFFF

    twin.cycle()
    put(rmap.STAGING_CLAIM, FORMER)
    twin.runtime.run(2)
    assert twin.state.staging_owner == FORMER
    put(rmap.STAGING_CLAIM, NEW)                          # another client claims and waits
    for k in range(1, 8):                                 # 0.7 s of the owner staging: a page every 0.1 s
        if paging:
            put(rmap.PAGE_CONTROL, 0, 1)                  # page 0, 1 LREAL, window -> aShadow
            put(rmap.PAGE_CONTROL + 1, 1, 1)
            put(rmap.PAGE_CONTROL + 2, 1, 1)
            put(rmap.PAGE_CONTROL + 3, k, 1)              # nPageSeq last: the request
        assert twin.runtime.run(100) == 100, twin.fault
    assert twin.state.staging_owner == (FORMER if paging else NEW)
