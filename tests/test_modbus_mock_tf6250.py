"""The Modbus mock behaves as TF6250 in front of a stopped or restarting PLC, checked with a plain pymodbus
client: a stopped task keeps its registers readable and writable but nothing moves (the cycle counter in
``stState`` stands still); while the runtime boots after a restart the server answers exception 4
(server device failure) and then serves again; during the restart itself nothing listens.

Register offsets are ST_CompTableModbusArea's (plc/DUTs): stState at 140, its nCycle (UDINT, low word
first) at 144..145, nCommitToken at 132..133; base 16#3000.
"""

from __future__ import annotations

import time

from pymodbus.client import ModbusTcpClient

from pmcal.bridge.simulator.faults import Fault, Kind, Point
from pmcal.bridge.simulator.modbus_mock import ModbusMockPlc
from tests.bridge_fixtures import during_restart, running

BASE = 0x3000
CYCLE = BASE + 144
COMMIT = BASE + 132


def _cycle(client) -> int:
    rr = client.read_holding_registers(CYCLE, count=2, device_id=1)
    assert not rr.isError()
    return rr.registers[0] | rr.registers[1] << 16


def test_a_stopped_plc_serves_frozen_registers():
    with running(ModbusMockPlc(lifetime_s=30.0)) as plc:
        c = ModbusTcpClient("127.0.0.1", port=plc.port, timeout=1, retries=0)
        assert c.connect()
        try:
            first = _cycle(c)
            time.sleep(0.05)
            assert _cycle(c) != first                            # running: the counter moves
            plc.stop_plc()
            time.sleep(0.02)
            frozen = _cycle(c)
            time.sleep(0.05)
            assert _cycle(c) == frozen                           # stopped: it stands still
            assert not c.write_registers(COMMIT, [0, 0], device_id=1).isError()   # memory still writable
            plc.start_plc()
            time.sleep(0.05)
            assert _cycle(c) != frozen
        finally:
            c.close()


def test_a_booting_runtime_answers_server_device_failure_then_serves():
    with running(ModbusMockPlc(lifetime_s=60.0, restart_s=1.2, boot_s=0.8)) as plc:
        def probe():
            c = ModbusTcpClient("127.0.0.1", port=plc.port, timeout=0.3, retries=0)
            try:
                if not c.connect():
                    return None                               # nothing listens yet
                rr = c.read_holding_registers(CYCLE, count=2, device_id=1)
                return getattr(rr, "exception_code", 0) if rr.isError() else 0
            finally:
                c.close()

        assert 4 in during_restart(plc, probe)                # TF6250 up, the PLC runtime not yet
        c = ModbusTcpClient("127.0.0.1", port=plc.port, timeout=1, retries=0)
        assert c.connect()
        try:
            first = _cycle(c)
            time.sleep(0.05)
            assert _cycle(c) != first
        finally:
            c.close()


def test_a_busy_server_answers_exception_6():
    with running(ModbusMockPlc(lifetime_s=30.0)) as plc:
        plc.faults.arm(Fault(Kind.BUSY, Point.BEFORE_STAGE, times=1))
        c = ModbusTcpClient("127.0.0.1", port=plc.port, timeout=1, retries=0)
        assert c.connect()
        try:
            rr = c.read_holding_registers(BASE, count=5, device_id=1)        # the information block
            assert rr.isError() and rr.exception_code == 6
            assert not c.read_holding_registers(BASE, count=5, device_id=1).isError()
        finally:
            c.close()


def test_only_holding_registers_reach_the_m_area():
    """TF6250's default mapping (Infosys, TF6250 "Default Configuration",
    /content/1033/tf6250_tc3_modbus_tcp/192746507.html) puts only holding registers 16#3000..16#5FFF on
    %M: input registers, coils and discrete inputs at the same addresses are other ADS areas (%I, %QX,
    %IX), never ST_CompTableModbusArea. A coil write there must not flip a bit of the area, an input
    register read must not return it; a function TF6250 lacks (FC 22, mask write) is exception 1."""
    with running(ModbusMockPlc(lifetime_s=30.0)) as plc:
        c = ModbusTcpClient("127.0.0.1", port=plc.port, timeout=1, retries=0)
        assert c.connect()
        try:
            magic = c.read_holding_registers(BASE, count=1, device_id=1).registers[0]
            assert magic == 0x504D
            for rr in (c.read_input_registers(BASE, count=1, device_id=1),
                       c.read_coils(BASE, count=16, device_id=1),
                       c.read_discrete_inputs(BASE, count=16, device_id=1),
                       c.write_coil(BASE, True, device_id=1),
                       c.write_coils(BASE, [True] * 8, device_id=1)):
                assert rr.isError() and rr.exception_code == 2, rr
            rr = c.mask_write_register(address=BASE, and_mask=0, or_mask=0xFFFF, device_id=1)
            assert rr.isError() and rr.exception_code == 1
            assert c.read_holding_registers(BASE, count=1, device_id=1).registers == [0x504D]
            assert not c.write_register(COMMIT, 0, device_id=1).isError()          # FC 6 reaches %M
        finally:
            c.close()
