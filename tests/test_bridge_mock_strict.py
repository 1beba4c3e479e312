"""The mocks are as strict as the hardware (issue 12, Deliver 7), checked with plain pyads / pymodbus
clients rather than the project's links.

ADS: a TwinCAT router answers a packet for another AMS NetID with error 7 (target machine not found)
and one for a port without ADS server with error 6 (target port not found) — Beckhoff InfoSys "ADS
Return Codes"; the texts are pyads.errorcodes'. Modbus: TF6250 answers with the exception codes of the
Modbus application protocol: 2 (illegal data address) outside the mapped area, 3 (illegal data value)
for a quantity over the function code's limit (FC3: 125, FC16: 123 registers).
"""

from __future__ import annotations

import socket
import struct

import pytest
from pymodbus.client import ModbusTcpClient

from pmcal.bridge.simulator.ads_mock import AdsMockPlc
from pmcal.bridge.errors import LinkError
from pmcal.bridge.ads_map import AdsMap
from pmcal.bridge.simulator.modbus_mock import ModbusMockPlc
from tests.bridge_fixtures import ads_link, ads_state_code, running


_read_state = ads_state_code


def test_ads_mock_answers_only_its_own_netid_and_port():
    with running(AdsMockPlc(lifetime_s=30.0)) as plc:
        assert _read_state(plc.netid, 851, plc) == 0
        assert _read_state(plc.netid, 852, plc) == 6                        # target port not found
        other = ".".join(["10", "250", "250", "250", "1", "1"])
        assert other != plc.netid
        assert _read_state(other, 851, plc) == 7                            # target machine not found
        assert plc.writes == 0


@pytest.mark.parametrize("port, code", [(852, 6)])
def test_link_names_the_routing_problem(port, code):
    with running(AdsMockPlc(lifetime_s=30.0)) as plc:
        link = ads_link(plc, amap=AdsMap(ams_port=port))
        with pytest.raises(LinkError, match=f"ADS error {code}.*--ams-port"):
            with link:
                link.check_interface()


def _raw(port: int, fc: int, address: int, count: int) -> tuple[int, int]:
    """One Modbus TCP request as bytes (MBAP + PDU); returns (function code, exception code) of the answer."""
    pdu = struct.pack(">BHH", fc, address, count)
    if fc == 16:
        pdu += struct.pack(">B", (2 * count) & 0xFF) + bytes(2 * count)
    frame = struct.pack(">HHHB", 0x1234, 0, len(pdu) + 1, 1) + pdu
    with socket.create_connection(("127.0.0.1", port), timeout=2.0) as s:
        s.sendall(frame)
        head = s.recv(9)
        return head[7], head[8]


def test_modbus_mock_exception_codes_are_tf6250s():
    with running(ModbusMockPlc(lifetime_s=30.0)) as plc:
        c = ModbusTcpClient("127.0.0.1", port=plc.port, timeout=1, retries=0)
        c.connect()
        try:
            base, end = plc.rmap.base, plc.rmap.base + plc.rmap.area_size
            assert not c.read_holding_registers(base, count=125, device_id=1).isError()
            # pymodbus' client refuses oversize requests itself: send those as raw frames
            assert _raw(plc.port, 3, base, 126) == (0x83, 3)
            assert _raw(plc.port, 16, base + plc.rmap.WINDOW, 124) == (0x90, 3)
            assert c.read_holding_registers(end, count=1, device_id=1).exception_code == 2
            assert c.read_holding_registers(end - 1, count=2, device_id=1).exception_code == 2
            assert c.write_registers(base - 1, [0], device_id=1).exception_code == 2
            # a PLC-owned register is written as TF6250 would; the PLC rewrites it next cycle
            assert not c.write_registers(base + plc.rmap.ACTIVE_HEADER, [7], device_id=1).isError()
        finally:
            c.close()
