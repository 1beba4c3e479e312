"""Modbus suite: the real pymodbus client against a real pymodbus server (SimDevice) on loopback."""

from __future__ import annotations

import time

import hashlib

import numpy as np
import pytest
from pymodbus.client import ModbusTcpClient

from pmcal.bridge.errors import DeviceError, InterfaceError, LinkError, WriteNotAllowed
from pmcal.bridge.simulator.faults import Fault, Kind, Point
from pmcal.bridge.modbus import ModbusLink, parse_host_port
from pmcal.bridge.modbus_map import FC16_MAX, ModbusMap, from_registers, to_registers
from pmcal.bridge.simulator.modbus_mock import ModbusMockPlc
from pmcal.bridge.plc_types import HEADER_SIZE, LOOKUP_WRITES, SHADOW_SIZE, Header, LookupResult, shadow_rows
from pmcal.bridge.transfer import PushOptions, push
from pmcal.errors import InputError
from tests.bridge_fixtures import (BIG_TABLE_ACK_S, BIG_TABLE_TIMEOUT_S, TIMEOUT_S, assert_within_cycle_budget,  # noqa: F401
                                   make_table, modbus_link, modbus_plc, running)

#: a small window so that modest tables cross many pages
SMALL = ModbusMap(window_lreals=250)


def test_round_trip_100x100x2_bit_exact(modbus_plc):
    table = make_table(version=1, n_phi=100, n_theta=100)
    rep = push(modbus_link(modbus_plc, timeout_s=BIG_TABLE_TIMEOUT_S), table, PushOptions(ack_timeout_s=BIG_TABLE_ACK_S))
    assert (rep.result, rep.active_version, rep.attempts) == ("ok", 1, 1)
    header, values = modbus_plc.twin.active_table()
    assert values.tobytes() == table.values.tobytes() and header == Header.of(table)
    sent = Header.of(table).pack() + shadow_rows(table)
    assert rep.bytes_sent == HEADER_SIZE + SHADOW_SIZE == len(sent)     # 80 124 registers
    assert rep.sha256_sent == hashlib.sha256(sent).hexdigest()
    assert_within_cycle_budget(modbus_plc)


def test_registers_are_the_twincat_memory_image():
    # LREAL 1.0 is 00 00 00 00 00 00 F0 3F in memory; register k holds bytes 2k, 2k+1 (little-endian word)
    regs = to_registers(np.array([1.0]).tobytes())
    assert regs == [0, 0, 0, 0x3FF0]
    assert regs == ModbusTcpClient.convert_to_registers([1.0], ModbusTcpClient.DATATYPE.FLOAT64, word_order="little")
    data = np.random.default_rng(4).normal(size=500).tobytes()
    assert from_registers(to_registers(data)) == data


def test_paged_window_moves_many_pages_bit_exact():
    table = make_table(version=1, n_phi=37, n_theta=13)
    with running(ModbusMockPlc(rmap=SMALL, lifetime_s=60.0)) as plc:
        assert len(SMALL.pages(table.values.size)) == 4             # 962 LREALs in pages of 250
        rep = push(modbus_link(plc), table)
        assert rep.result == "ok"
        assert plc.twin.active_table()[1].tobytes() == table.values.tobytes()
        with modbus_link(plc) as link:
            assert link.read_back(8 * table.values.size)[1] == shadow_rows(table)


def test_page_outside_the_shadow_buffer_is_refused(modbus_plc):
    with modbus_link(modbus_plc) as link:
        with pytest.raises(DeviceError, match="page 7"):
            link._page(7, 3000, 1, link._page_seq())          # 7 * 3000 LREAL > 20 000


def test_request_sizes_respect_the_function_code_limits(modbus_plc):
    with pytest.raises(ValueError):
        ModbusMap(chunk=124)
    client = ModbusTcpClient("127.0.0.1", port=modbus_plc.port, timeout=1, retries=0)
    client.connect()
    try:
        base = modbus_plc.rmap.base + modbus_plc.rmap.WINDOW
        assert not client.write_registers(base, [0] * FC16_MAX, device_id=1).isError()
        too_long = client.write_registers(base, [0] * 125, device_id=1)
        assert too_long.isError()
        # TF6250 maps registers onto PLC memory with no owner: a write to the PLC's answers is accepted,
        # and the PLC overwrites it at the end of its next cycle
        state = modbus_plc.rmap.base + modbus_plc.rmap.STATE
        assert not client.write_registers(state, [0xFFFF], device_id=1).isError()
        time.sleep(0.05)
        assert client.read_holding_registers(state, count=1, device_id=1).registers[0] != 0xFFFF
    finally:
        client.close()


@pytest.mark.parametrize("what", ["nan", "step", "stale"])
def test_bad_tables_are_refused_before_anything_is_written(modbus_plc, what):
    modbus_plc.twin.seed(make_table(version=5))
    table = make_table(version=6, n_phi=9 if what == "step" else 37)
    if what == "nan":
        table.values[0, 1, 1] = np.nan
    elif what == "stale":
        table = make_table(version=4)
    with pytest.raises(InputError):
        push(modbus_link(modbus_plc), table)
    assert modbus_plc.writes == 0 and modbus_plc.twin.state.active_version == 5


def test_dry_run_writes_nothing(modbus_plc):
    rep = push(modbus_link(modbus_plc, writes=frozenset()), make_table(version=1), PushOptions(dry_run=True))
    assert rep.result == "dry_run" and modbus_plc.writes == 0 and modbus_plc.requests > 0


def test_writes_outside_the_allow_list_never_leave_the_client(modbus_plc):
    with modbus_link(modbus_plc) as link:
        with pytest.raises(WriteNotAllowed, match="allow-list"):
            link.write_symbol("lookup_in", bytes(32))
        with pytest.raises(WriteNotAllowed):
            link._write(modbus_plc.rmap.STATE, [0])
        with pytest.raises(WriteNotAllowed):                      # runs past the window's end
            link._write(modbus_plc.rmap.WINDOW + 4 * modbus_plc.rmap.window_lreals - 2, [0] * 4)
    assert modbus_plc.writes == 0


def test_interface_check_refuses_another_register_map(modbus_plc):
    with pytest.raises(InterfaceError, match="register map"):
        push(ModbusLink(modbus_plc.host, modbus_plc.port, rmap=SMALL, timeout_s=TIMEOUT_S), make_table(version=1))
    assert modbus_plc.writes == 0


def test_interface_check_refuses_a_plc_that_does_not_cycle(modbus_plc):
    modbus_plc.twin.stop()
    with pytest.raises(InterfaceError, match="not running"):
        push(modbus_link(modbus_plc, page_timeout_s=0.05), make_table(version=1))
    assert modbus_plc.writes == 0


def test_one_lost_reply_is_survived(modbus_plc):
    modbus_plc.faults.arm(Fault(Kind.NO_REPLY, Point.MID_STAGE, times=1))
    table = make_table(version=1)
    rep = push(modbus_link(modbus_plc), table)
    assert (rep.result, rep.attempts, modbus_plc.faults.fired) == ("ok", 2, 1)
    assert modbus_plc.twin.active_table()[1].tobytes() == table.values.tobytes()


def test_no_server_is_a_link_error():
    with running(ModbusMockPlc(lifetime_s=30.0)) as plc:
        port = plc.port
    with pytest.raises(LinkError, match="refused or unreachable"):
        push(ModbusLink("127.0.0.1", port, timeout_s=TIMEOUT_S), make_table(version=1), PushOptions(attempts=2))


def test_lookup_over_modbus_gives_the_interpolated_targets(modbus_plc):
    table = make_table(version=2)
    push(modbus_link(modbus_plc), table)
    ref = table.interpolate([123.4, 0.0], [33.3, 60.0])
    with modbus_link(modbus_plc, writes=LOOKUP_WRITES) as link:
        for k, (phi, theta) in enumerate([(123.4, 33.3), (0.0, 60.0)]):
            out = link.lookup(phi, theta)
            assert (out.result, out.table_version, out.m1_deg, out.m2_deg) == (
                LookupResult.OK, 2, ref[k, 0], ref[k, 1])


def test_host_port_parsing():
    assert parse_host_port("plc.local") == ("plc.local", 502)
    assert parse_host_port("127.0.0.1:1502") == ("127.0.0.1", 1502)
    for bad in ("", ":502", "h:0", "h:x", "127.0.0.1:502:3", "::1", "host name:502"):   # not a host: exit 2
        with pytest.raises(ValueError):
            parse_host_port(bad)


def test_slow_answers_within_the_time_out_are_fine(modbus_plc):
    modbus_plc.faults.arm(Fault(Kind.DELAY, Point.AFTER_STAGE, delay_s=0.05, times=3))
    rep = push(modbus_link(modbus_plc, timeout_s=1.0), make_table(version=1))
    assert (rep.result, rep.attempts, modbus_plc.faults.fired) == ("ok", 1, 3)
