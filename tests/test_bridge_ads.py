"""ADS suite: the real pyads client against the framed, strict pyads.testserver mock on loopback."""

from __future__ import annotations

import ctypes
import hashlib
import json
import time

import numpy as np
import pyads
import pytest
from pyads import constants

from pmcal.bridge.ads import AdsLink
from pmcal.bridge.ads_map import AdsMap, AdsTarget
from pmcal.bridge.simulator.ads_mock import AdsMockPlc
from pmcal.bridge.errors import AckTimeout, InterfaceError, LinkError, WriteNotAllowed
from pmcal.bridge.simulator.faults import Fault, Kind, Point
from pmcal.bridge.plc_types import (HEADER_SIZE, LOOKUP_WRITES, PUSH_WRITES, SHADOW_SIZE, SYMBOLS, Header,
                              LookupResult, State, Status, Symbol, shadow_rows)
from pmcal.bridge.transfer import PushOptions, push
from pmcal.errors import InputError
from tests.bridge_fixtures import (BIG_TABLE_ACK_S, BIG_TABLE_TIMEOUT_S, TIMEOUT_S, ads_link, ads_plc,  # noqa: F401
                                   assert_within_cycle_budget, make_table, running)

FAST = PushOptions(attempts=2, ack_timeout_s=1.0, idle_timeout_s=1.0)


def test_round_trip_100x100x2_bit_exact(ads_plc, tmp_path):
    table = make_table(version=1, n_phi=100, n_theta=100)
    audit = tmp_path / "audit.log"
    rep = push(ads_link(ads_plc, timeout_s=BIG_TABLE_TIMEOUT_S), table, PushOptions(ack_timeout_s=BIG_TABLE_ACK_S),
               audit_path=audit)
    assert (rep.result, rep.previous_version, rep.active_version, rep.status, rep.attempts) == ("ok", 0, 1, "OK", 1)
    header, values = ads_plc.twin.active_table()
    assert values.tobytes() == table.values.tobytes() and header == Header.of(table)
    # what was sent: the header and the whole 160 000-byte aShadow, far beyond the stock server's 4 kB
    sent = Header.of(table).pack() + shadow_rows(table)
    assert rep.bytes_sent == HEADER_SIZE + SHADOW_SIZE == len(sent)
    assert rep.sha256_sent == hashlib.sha256(sent).hexdigest()
    assert_within_cycle_budget(ads_plc)
    with ads_link(ads_plc) as link:
        back_header, back = link.read_back(SHADOW_SIZE)
    assert back_header + back == sent
    line = json.loads(audit.read_text().splitlines()[-1])
    assert (line["event"], line["result"], line["version"], line["sha256_sent"]) == (
        "push", "ok", 1, rep.sha256_sent)
    assert line["crc32"] == f"0x{table.crc32():08X}"


def test_each_push_replaces_the_active_table_and_same_content_is_a_no_op(ads_plc):
    link = ads_link(ads_plc)
    for v in (1, 2, 3):
        assert push(link, make_table(version=v, offset_deg=0.01 * v)).active_version == v
    writes = ads_plc.writes
    rep = push(link, make_table(version=3, offset_deg=0.03))
    assert rep.result == "already_active" and ads_plc.writes == writes
    st = ads_plc.twin.state
    assert (st.active_version, st.ack_token, st.state) == (3, 0, State.IDLE)   # released after the ack


@pytest.mark.parametrize("what", ["nan", "range", "step", "grid", "stale"])
def test_bad_tables_are_refused_before_anything_is_written(ads_plc, what):
    good = make_table(version=5)
    ads_plc.twin.seed(good)
    table = make_table(version=6, n_phi=9 if what == "step" else 37)
    if what == "nan":
        table.values[3, 3, 0] = np.nan
    elif what == "range":
        table.values[3, 3, 1] = 90.0
    elif what == "grid":
        table = make_table(version=6, n_phi=101, n_theta=3)
    elif what == "stale":
        table = make_table(version=5, offset_deg=0.5)
    with pytest.raises(InputError):
        push(ads_link(ads_plc), table)
    assert ads_plc.writes == 0
    assert ads_plc.twin.state.active_version == 5


def test_dry_run_writes_nothing(ads_plc):
    table = make_table(version=1)
    rep = push(ads_link(ads_plc, writes=frozenset()), table, PushOptions(dry_run=True))
    assert rep.result == "dry_run" and rep.bytes_sent == 0 and ads_plc.requests > 0
    assert ads_plc.writes == 0 and ads_plc.twin.state.active_version == 0
    assert rep.sha256_sent == push(ads_link(ads_plc), table).sha256_sent      # what a real push then sends


def test_writes_outside_the_allow_list_never_leave_the_client(ads_plc):
    with ads_link(ads_plc) as link:
        with pytest.raises(WriteNotAllowed, match="allow-list"):
            link.write_symbol("lookup_in", bytes(24))
        with pytest.raises(WriteNotAllowed):
            link.write_symbol("state", bytes(24))
        with pytest.raises(WriteNotAllowed, match="bytes"):
            link.write_symbol("commit", bytes(8))
    assert ads_plc.writes == 0


def test_writes_by_handle_are_taken_as_twincat_takes_them(ads_plc):
    """TwinCAT writes the bytes sent into the symbol's first bytes: a short write changes only those,
    pyads' write of the (1-D, format 4) array with its guessed type writes it all, a longer one is refused."""
    plc = pyads.Connection(ads_plc.netid, 851, f"127.0.0.1:{ads_plc.port}")
    plc.open()
    plc.set_timeout(1000)
    t = ctypes.c_double * 20000
    try:
        plc.write_by_name("GVL_CompTable.aShadow", [1.0] * 10, pyads.PLCTYPE_ARR_LREAL(10))     # 10 of 20 000
        back = np.frombuffer(bytes(plc.read_by_name("GVL_CompTable.aShadow", t, return_ctypes=True)), "<f8")
        assert np.array_equal(back[:10], np.ones(10)) and not back[10:].any()
        plc.write_by_name("GVL_CompTable.aShadow", [2.0] * 20000)   # 1-D: pyads' guessed type is right
        back = np.frombuffer(bytes(plc.read_by_name("GVL_CompTable.aShadow", t, return_ctypes=True)), "<f8")
        assert np.array_equal(back, np.full(20000, 2.0))
        with pytest.raises(pyads.ADSError) as exc:                  # more than the symbol holds
            plc.write_by_name("GVL_CompTable.nCommitToken", 1, pyads.PLCTYPE_ULINT)
        assert exc.value.err_code == 1797
        with pytest.raises(pyads.ADSError) as exc:
            plc.read_by_name("GVL_CompTable.nNoSuchThing", pyads.PLCTYPE_UDINT)
        assert exc.value.err_code == 1808
        if "stState" in ads_plc.read_only:               # {attribute 'symbol' := 'read'} in the GVL
            with pytest.raises(pyads.ADSError) as exc:
                plc.write_by_name("GVL_CompTable.stState", [0] * 24, pyads.PLCTYPE_BYTE * 24)
            assert exc.value.err_code == 1796
        else:                                            # TwinCAT accepts it; the PLC overwrites it next cycle
            plc.write_by_name("GVL_CompTable.stState", [0xFF] * 24, pyads.PLCTYPE_BYTE * 24)
            time.sleep(0.05)
            assert plc.read_by_name("GVL_CompTable.stState", pyads.PLCTYPE_BYTE * 24) != [0xFF] * 24
        data = np.random.default_rng(3).normal(size=20000)
        plc.write_by_name("GVL_CompTable.aShadow", t.from_buffer_copy(data.tobytes()), t)
        back = plc.read_by_name("GVL_CompTable.aShadow", t, return_ctypes=True)
        assert bytes(back) == data.tobytes()
    finally:
        plc.close()
    assert ads_plc.twin.state.active_version == 0


def test_interface_check_refuses_a_stopped_plc(ads_plc):
    ads_plc.ads_state = constants.ADSSTATE_STOP
    with pytest.raises(InterfaceError, match="not in RUN"):
        push(ads_link(ads_plc), make_table(version=1))
    assert ads_plc.writes == 0


@pytest.mark.parametrize("change", ["size", "missing"])
def test_interface_check_refuses_another_plc_program(change):
    symbols = tuple(s for s in SYMBOLS if not (change == "missing" and s.key == "lookup_out"))
    if change == "size":
        symbols = tuple(Symbol(s.key, s.st_name, "ARRAY [0..49,0..99,0..1] OF LREAL", 80000, s.written_by)
                        if s.key == "shadow" else s for s in symbols)
    with running(AdsMockPlc(symbols=symbols, lifetime_s=60.0)) as plc:
        with pytest.raises(InterfaceError, match="aShadow" if change == "size" else "stLookupOut"):
            push(ads_link(plc), make_table(version=1))
        assert plc.writes == 0


def test_ack_timeout_withdraws_the_commit(ads_plc):
    ads_plc.twin.seed(make_table(version=1))
    ads_plc.twin.motion_idle = False                      # the machine keeps moving
    with pytest.raises(AckTimeout, match="withdrawn, active version stays 1") as exc:
        push(ads_link(ads_plc), make_table(version=2), PushOptions(ack_timeout_s=0.2))
    assert exc.value.report.result == "failed"
    st = ads_plc.twin.state
    assert (st.active_version, st.status, st.state) == (1, Status.WITHDRAWN, State.IDLE)


def test_one_dropped_link_is_reopened_and_the_transfer_restarted(ads_plc):
    ads_plc.faults.arm(Fault(Kind.DROP, Point.MID_STAGE, times=1))
    table = make_table(version=1, n_phi=100, n_theta=100)
    rep = push(ads_link(ads_plc, timeout_s=BIG_TABLE_TIMEOUT_S), table, PushOptions(ack_timeout_s=BIG_TABLE_ACK_S))
    assert (rep.result, rep.attempts, ads_plc.faults.fired) == ("ok", 2, 1)
    assert ads_plc.twin.active_table()[1].tobytes() == table.values.tobytes()


def test_slow_answers_within_the_time_out_are_fine(ads_plc):
    ads_plc.faults.arm(Fault(Kind.DELAY, Point.MID_STAGE, delay_s=0.05))
    rep = push(ads_link(ads_plc, timeout_s=1.0), make_table(version=1))
    assert (rep.result, rep.attempts) == ("ok", 1) and ads_plc.faults.fired == 1


def test_no_plc_listening_is_a_link_error():
    with running(AdsMockPlc(lifetime_s=30.0)) as plc:
        address = plc.address
    with pytest.raises(LinkError, match="gave up after 2 attempts.; nothing committed"):
        push(AdsLink(address, timeout_s=TIMEOUT_S), make_table(version=1), FAST)


def test_lookup_over_ads_gives_the_interpolated_targets(ads_plc):
    table = make_table(version=4, n_phi=100, n_theta=100)
    push(ads_link(ads_plc, timeout_s=BIG_TABLE_TIMEOUT_S), table, PushOptions(ack_timeout_s=BIG_TABLE_ACK_S))
    phi, theta = np.array([0.0, 17.3, 359.9, 200.0]), np.array([0.0, 41.7, 60.0, 12.5])
    ref = table.interpolate(phi, theta)
    with ads_link(ads_plc, writes=LOOKUP_WRITES) as link:
        for k in range(len(phi)):
            out = link.lookup(phi[k], theta[k])
            assert (out.result, out.table_version, out.m1_deg, out.m2_deg) == (
                LookupResult.OK, 4, ref[k, 0], ref[k, 1])
        assert link.lookup(10.0, 75.0).result == LookupResult.OUT_OF_GRID
        with pytest.raises(WriteNotAllowed):
            link.write_commit(9)


def test_target_parsing():
    t = AdsTarget.parse("5.80.201.232.1.1@192.168.1.10")
    assert (t.netid, t.host, t.tcp_port) == ("5.80.201.232.1.1", "192.168.1.10", 48898)
    assert AdsTarget.parse("1.2.3.4.1.1@plc-7:4000").tcp_port == 4000
    for bad in ("1.2.3.4.1@host", "1.2.3.4.1.1", "1.2.3.4.1.300@h", "1.2.3.4.1.1@h:0"):
        with pytest.raises(ValueError):
            AdsTarget.parse(bad)
    assert AdsMap().name("shadow") == "GVL_CompTable.aShadow" and PUSH_WRITES.isdisjoint(LOOKUP_WRITES)
