"""The table kind, motors and machine are pinned on the PLC itself (GVL_CompTableParam.MACHINE, NMOTORS,
CORRECTIONS): a client without any of the bridge's checks cannot make the PLC take a correction table on
a PLC whose motion code expects motor commands, a table of another machine, or one with other motors; a
PLC whose MACHINE or NMOTORS is not set serves nothing. The sample motion code (PRG_CompTableMotionSample,
FB_CompTableTargets) checks eResult, the kind and the motors before it moves, run in the interpreter.

ADS: a plain pyads client writes the GVL symbols by name. Modbus: a plain pymodbus client writes the
registers of ST_CompTableModbusArea at the addresses docs/bridge.md documents (typed here again, not taken
from pmcal's register map), pages the rows through the window and waits for the PLC's page echo.
"""

from __future__ import annotations

import ctypes
import time
from dataclasses import replace

import numpy as np
import pyads
import pytest

from pmcal.bridge.comptable import Axis, CompTable, Motor
from pmcal.bridge.simulator.plc_runtime import PlcRuntime, PlcTwin
from pmcal.bridge.simulator.plc_runtime.comptable_plc import machine_constants
from pmcal.bridge.plc_types import (SHADOW_SIZE, Header, LookupIn, LookupOut, LookupResult, State, Status,
                                   shadow_rows)
from tests.bridge_fixtures import make_table, raw_commit, running

TOKEN = 0x8A5E0001


class PlainAds:
    """A plain pyads client: GVL_CompTable symbols by name, no interface check, no table check."""

    def __init__(self, plc) -> None:
        self.conn = pyads.Connection(plc.netid, 851, f"{plc.host}:{plc.port}")

    def __enter__(self):
        self.conn.open()
        return self

    def __exit__(self, *exc) -> None:
        self.conn.close()

    def write_claim(self, token: int) -> None:
        self.conn.write_by_name("GVL_CompTable.nStagingClaim", token, pyads.PLCTYPE_UDINT)

    def write_commit(self, token: int) -> None:
        self.conn.write_by_name("GVL_CompTable.nCommitToken", token, pyads.PLCTYPE_UDINT)

    def stage(self, header: bytes, rows: bytes) -> None:
        self.conn.write_by_name("GVL_CompTable.stShadowHeader", list(header), ctypes.c_uint8 * len(header))
        data = np.frombuffer(rows + bytes(SHADOW_SIZE - len(rows)), dtype="<f8")
        self.conn.write_by_name("GVL_CompTable.aShadow", data.tolist(), pyads.PLCTYPE_ARR_LREAL(len(data)))


class PlainModbus:
    """A plain pymodbus client of ST_CompTableModbusArea (holding registers from 16#3000, unit 1; register k
    of a value = bytes 2k, 2k+1 of its little-endian image): no interface check, no table check, no bridge
    code."""

    BASE, HEADER, COMMIT, PAGE_CONTROL, PAGE_ACK, CLAIM, WINDOW = 0x3000, 8, 132, 134, 138, 324, 384
    WINDOW_LREALS, CHUNK = 2970, 120

    def __init__(self, plc) -> None:
        from pymodbus.client import ModbusTcpClient

        self.client = ModbusTcpClient(plc.host, port=plc.port, timeout=5)

    def __enter__(self):
        assert self.client.connect()
        return self

    def __exit__(self, *exc) -> None:
        self.client.close()

    def _write(self, offset: int, regs) -> None:
        regs = [int(r) for r in regs]
        for k in range(0, len(regs), self.CHUNK):
            rr = self.client.write_registers(self.BASE + offset + k, regs[k:k + self.CHUNK], device_id=1)
            assert not rr.isError(), rr

    def _read(self, offset: int, count: int) -> list[int]:
        rr = self.client.read_holding_registers(self.BASE + offset, count=count, device_id=1)
        assert not rr.isError(), rr
        return list(rr.registers)

    def write_claim(self, token: int) -> None:
        self._write(self.CLAIM, [token & 0xFFFF, token >> 16])

    def write_commit(self, token: int) -> None:
        self._write(self.COMMIT, [token & 0xFFFF, token >> 16])

    def stage(self, header: bytes, rows: bytes) -> None:
        self._write(self.HEADER, np.frombuffer(header, dtype="<u2"))
        regs = np.frombuffer(rows, dtype="<u2")
        seq = self._read(self.PAGE_ACK, 1)[0]
        n = len(rows) // 8
        for page in range((n + self.WINDOW_LREALS - 1) // self.WINDOW_LREALS):
            count = min(self.WINDOW_LREALS, n - page * self.WINDOW_LREALS)
            start = page * self.WINDOW_LREALS * 4
            self._write(self.WINDOW, regs[start:start + 4 * count])
            seq = (seq + 1) & 0xFFFF or 1
            self._write(self.PAGE_CONTROL, [page, count, 1, seq])          # 1: window -> aShadow
            deadline = time.monotonic() + 10.0
            while self._read(self.PAGE_ACK, 2) != [seq, 0]:
                assert time.monotonic() < deadline, "the PLC did not take the page"
                time.sleep(0.005)


def _corrections(machine: str = "ocpm_2dof", version: int = 6) -> CompTable:
    """A valid correction table (nReference 2) for a 2-motor machine: +0.25 deg everywhere."""
    axes = [Axis("phi", "deg", 0.0, 360.0, 37), Axis("theta", "deg", 0.0, 60.0, 13)]
    motors = [Motor("m1", "deg", -0.5, 0.5, 0.2), Motor("m2", "deg", -0.5, 0.5, 0.2)]
    return CompTable(machine=machine, version=version, axes=axes, motors=motors,
                     values=np.full((37, 13, 2), 0.25), reference="controller").validate()


def _three_motors(version: int = 6) -> CompTable:
    """A valid table of absolute commands for three motors, named for the OCPM."""
    axes = [Axis("phi", "deg", 0.0, 360.0, 37), Axis("theta", "deg", 0.0, 60.0, 13)]
    motors = [Motor(f"m{k + 1}", "deg", -120.0, 60.0, 12.0) for k in range(3)]
    return CompTable(machine="ocpm_2dof", version=version, axes=axes, motors=motors,
                     values=np.zeros((37, 13, 3))).validate()


def _other_machine(version: int = 6) -> CompTable:
    return replace(make_table(version=version), machine="planar_2dof").validate()


CASES = [pytest.param(_corrections, Status.KIND_MISMATCH, id="correction table to a command PLC"),
         pytest.param(_other_machine, Status.MACHINE_MISMATCH, id="table of another machine"),
         pytest.param(_three_motors, Status.MOTORS_MISMATCH, id="table with three motors")]


def _mock(transport: str):
    from pmcal.bridge.simulator.ads_mock import AdsMockPlc
    from pmcal.bridge.simulator.modbus_mock import ModbusMockPlc

    return (AdsMockPlc if transport == "ads" else ModbusMockPlc)(lifetime_s=120.0)


@pytest.mark.parametrize("transport", ["ads", "modbus"])
@pytest.mark.parametrize("make, status", CASES)
def test_the_plc_refuses_a_table_of_another_kind_machine_or_motors(transport, make, status):
    table = make()
    with running(_mock(transport)) as plc:                # ocpm_2dof, 2 motors, motor commands
        plc.twin.seed(make_table(version=5))
        with (PlainAds(plc) if transport == "ads" else PlainModbus(plc)) as ln:
            st = raw_commit(plc, ln, Header.of(table).pack(), shadow_rows(table), TOKEN)
        assert (st.status, st.active_version) == (status, 5), st
        assert plc.twin.active_table()[1].tobytes() == make_table(version=5).values.tobytes()
        # and a table that fits is taken from the same client
        good = make_table(version=7, offset_deg=0.1)
        with (PlainAds(plc) if transport == "ads" else PlainModbus(plc)) as ln:
            st = raw_commit(plc, ln, Header.of(good).pack(), shadow_rows(good), TOKEN + 2)
        assert (st.status, st.active_version) == (Status.OK, 7)


def test_a_correction_plc_takes_correction_tables_only():
    twin = PlcTwin(machine="ocpm_2dof", motors=2, corrections=True)
    twin.seed(_corrections(version=3))
    assert twin.started and twin.state.active_version == 3
    twin2 = PlcTwin(machine="ocpm_2dof", motors=2, corrections=True)
    twin2.seed(make_table(version=3))                       # a command table in the store: dropped at start-up
    assert (twin2.state.status, twin2.state.active_version) == (Status.KIND_MISMATCH, 0)


@pytest.mark.parametrize("machine, motors", [("", 2), ("ocpm_2dof", 0)])
def test_an_unconfigured_plc_serves_nothing_and_says_so(machine, motors):
    twin = PlcTwin(machine=machine, motors=motors)
    twin.seed(make_table(version=3))                        # cannot finish: the start-up waits for the configuration
    st = twin.state
    assert (st.status, st.state, twin.started) == (Status.NOT_CONFIGURED, State.STARTING, False)
    twin.write_symbol("lookup_in", LookupIn((100.0, 30.0), 1).pack())
    twin.cycle()
    assert LookupOut.unpack(twin.read_symbol("lookup_out")).result == LookupResult.NO_TABLE
    twin.write_symbol("staging_claim", TOKEN.to_bytes(4, "little"))
    twin.cycle()
    twin.write_symbol("commit", TOKEN.to_bytes(4, "little"))
    twin.cycle()
    assert (twin.state.ack_token, twin.state.status) == (TOKEN, Status.NOT_CONFIGURED)


# ---- the sample motion code, run ----

def _sample(corrections: bool = False) -> PlcTwin:
    rt = PlcRuntime(task=("PRG_CompTable", "PRG_CompTableMotionSample"),
                    constants=machine_constants("ocpm_2dof", 2, corrections))
    return PlcTwin(runtime=rt)


def _start(twin: PlcTwin, x, nominal=(0.0, 0.0)):
    """A rising bStart with task point x; returns (moves, targets of M1, M2) as the axes were told."""
    rt = twin.runtime
    rt.write_value("PRG_CompTableMotionSample.bStart", False)
    twin.cycle()
    for k, v in enumerate(x):
        rt.write_value(f"PRG_CompTableMotionSample.aX[{k}]", v)
    for k, v in enumerate(nominal):
        rt.write_value(f"PRG_CompTableMotionSample.aNominal[{k}]", v)
    rt.write_value("PRG_CompTableMotionSample.bStart", True)
    assert twin.cycle(), twin.fault
    axes = [f"GVL_CompTableAxes.stAxisM{k}" for k in (1, 2)]
    return (rt.read_value(f"{axes[0]}.nSimMoves"), rt.read_value(f"{axes[0]}.fSimTarget"),
            rt.read_value(f"{axes[1]}.fSimTarget"))


def _lookup(twin: PlcTwin, x) -> LookupOut:
    seq = LookupOut.unpack(twin.read_symbol("lookup_out")).seq + 1
    twin.write_symbol("lookup_in", LookupIn(tuple(x), seq).pack())
    twin.cycle()
    return LookupOut.unpack(twin.read_symbol("lookup_out"))


def test_the_sample_motion_code_moves_to_the_lookup_targets():
    twin = _sample()
    table = make_table(version=4, offset_deg=0.3)
    twin.seed(table)
    x = (123.0, 33.0)
    want = _lookup(twin, x)
    assert want.result == LookupResult.OK and not want.correction
    moves, m1, m2 = _start(twin, x)
    assert (moves, m1, m2) == (1, want.m[0], want.m[1])     # bit for bit what FB_CompTableLookup answers
    assert np.allclose((m1, m2), table.lookup(np.array([x]))[0], rtol=0, atol=1e-9)


def test_the_sample_motion_code_does_not_move_on_a_table_of_the_wrong_kind():
    """The issue's case: a correction table (+0.25 deg) in the store of a PLC whose motion code takes motor
    commands (here written into the store directly, as a foreign ADS write would): the lookup answers OK
    with bCorrection TRUE and aM = 0.25; the sample refuses and nothing moves (it would have driven to
    0.25 deg instead of about -39 deg)."""
    twin = _sample()
    twin.seed(make_table(version=4))
    moves, m1, _ = _start(twin, (100.0, 30.0))
    assert moves == 1 and m1 < -10.0
    rt, corr = twin.runtime, _corrections(version=9)
    k = rt.read_value("GVL_CompTableStore.nActive")
    addr, _ = rt.locate(f"GVL_CompTableStore.aBuffer[{k}]")
    rows = shadow_rows(corr)
    rt.mem[addr:addr + len(rows)] = rows
    rt.write_bytes(f"GVL_CompTableStore.aHeader[{k}]", Header.of(corr).pack())
    got = _lookup(twin, (100.0, 30.0))
    assert (got.result, got.correction, got.m[0]) == (LookupResult.OK, True, 0.25)
    moves2, m1b, _ = _start(twin, (100.0, 30.0))
    assert (moves2, m1b) == (1, m1)                          # no new move, the old target stays
    assert rt.read_value("PRG_CompTableMotionSample.bRefused")


def test_the_sample_adds_corrections_to_the_controllers_nominal_ik():
    twin = _sample(corrections=True)
    twin.seed(_corrections(version=2))
    moves, m1, m2 = _start(twin, (100.0, 30.0), nominal=(-39.0, 12.5))
    assert (moves, m1, m2) == (1, -39.0 + 0.25, 12.5 + 0.25)


def test_the_sample_does_not_move_without_a_table():
    twin = _sample()
    assert _start(twin, (100.0, 30.0))[0] == 0
    assert twin.runtime.read_value("PRG_CompTableMotionSample.eRefusal") == LookupResult.NO_TABLE


def test_no_swap_from_the_start_of_a_move_until_it_is_over():
    """NcToPlc lags: a move the sample starts in cycle c shows in the axes' status only from c + 2 (the
    NC's cycles), so right after the start FB_CompTableMotionIdle still reads "standing still". The
    sample's bMovePending (Execute, MC_MoveAbsolute.Busy) keeps the manager from swapping from the start
    of the move until it is over; a commit waiting for motion swaps after it."""
    twin = _sample()
    rt = twin.runtime
    twin.seed(make_table(version=1))
    new = make_table(version=2, offset_deg=0.2)
    twin.write_symbol("staging_claim", TOKEN.to_bytes(4, "little"))
    twin.cycle()
    twin.write_symbol("shadow_header", Header.of(new).pack())
    twin.write_shadow_bytes(0, shadow_rows(new))
    twin.motion_idle = False                                # another axis job: the commit waits
    twin.write_symbol("commit", TOKEN.to_bytes(4, "little"))
    for _ in range(2_000):
        assert twin.cycle(), twin.fault
        if twin.state.state == State.WAIT_MOTION:
            break
    assert twin.state.state == State.WAIT_MOTION
    for k, v in enumerate((100.0, 30.0)):
        rt.write_value(f"PRG_CompTableMotionSample.aX[{k}]", v)
    rt.write_value("PRG_CompTableMotionSample.bStart", True)
    twin.cycle()                                            # cycle c: the sample starts the move
    assert rt.read_value("GVL_CompTableAxes.stAxisM1.nSimMoves") == 1
    twin.motion_idle = True                                 # the other job is over
    twin.cycle()                                            # c + 1: the NC has not reported the move yet
    assert rt.read_value("PRG_CompTable.fbMotionIdle.bIdle")        # the axes' status alone says idle ...
    assert twin.state.active_version == 1                           # ... and yet no swap
    rt.write_value("PRG_CompTableMotionSample.bStart", False)
    busy_cycles = 0
    while rt.read_value("PRG_CompTableMotionSample.fbMoveM1.Busy"):
        assert twin.state.active_version == 1, "swapped during a move"
        assert twin.cycle(), twin.fault
        busy_cycles += 1
    assert busy_cycles >= rt.move_cycles - 2
    for _ in range(200):                                    # the swap, the save in PersistTask, the ack
        twin.cycle()
        if twin.state.ack_token == TOKEN:
            break
    assert (twin.state.status, twin.state.active_version) == (Status.OK, 2)
