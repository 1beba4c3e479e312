"""A mock TwinCAT PLC over Modbus TCP: a pymodbus server (SimDevice) in front of the PLC twin.

The SimDevice's holding registers stand for the TF6250 mapping of ``stMbArea AT %MB0``: they are the
PLC's %M memory itself (:class:`ModbusArea`). Only the holding-register functions (FC 3, 6, 16, 23) reach
it, as with TF6250's default mapping: coils, discrete inputs and input registers (FC 1, 2, 4, 5, 15) are
other ADS areas there (%QX, %IX, the %I image), which this mock PLC does not have (exception 2), and a
function TF6250 does not implement (e.g. FC 22) answers exception 1. The ST of plc/ (FB_CompTableModbus,
called by PRG_CompTable with ``bUseModbus``) copies the bridge's inputs into GVL_CompTable, serves a page
request and copies the PLC's outputs back, every task cycle.
Every register of the mapped area can be written, as on TF6250 (the PLC overwrites its own outputs in
its next cycle). While the PLC is stopped the registers stay readable and writable but nothing moves
(the task does not run); while the runtime boots after a restart, requests answer exception 4
(server device failure: TF6250's ADS access to the PLC fails).

The server runs inside its own asyncio loop in a thread (pymodbus builds servers in a running loop),
on 127.0.0.1, ephemeral port by default, and shuts down at the mock's deadline.
"""

from __future__ import annotations

import asyncio
import threading
import time

from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from pmcal.bridge.simulator.faults import Kind, Point
from pmcal.bridge.simulator.mock import MockPlc
from pmcal.bridge.modbus_map import FC3_MAX, FC16_MAX, ModbusMap
from pmcal.bridge.simulator.plc_runtime import PlcTwin
from pmcal.bridge.plc_types import is_token

_FC_READ = (3, 23)
#: function codes of the TwinCAT Modbus TCP server (Infosys TcModbusSrv, https://infosys.beckhoff.com/content/1033/
#: tcmodbussrv/11379410187.html; FC 8, diagnostics, is answered by pymodbus itself): any other is exception 1
TF6250_FUNCTIONS = (1, 2, 3, 4, 5, 6, 15, 16, 23)
#: the holding-register functions: with TF6250's default mapping only these reach the %M area (16#3000..16#5FFF
#: -> index group 16#4020); coils and discrete inputs are %QX/%IX bits, input registers the %I image (Infosys
#: TF6250 "Default Configuration", https://infosys.beckhoff.com/content/1033/tf6250_tc3_modbus_tcp/192746507.html)
FC_HOLDING = (3, 6, 16, 23)


class ModbusArea:
    """ST_CompTableModbusArea as the Modbus server sees it: the registers are the PLC's %M memory
    (``stMbArea AT %MB0``, TF6250's default map), and the ST maps them onto GVL_CompTable in each task
    cycle (PRG_CompTable with ``bUseModbus``: FB_CompTableModbus.M_CopyIn / M_CopyOut)."""

    def __init__(self, rmap: ModbusMap, twin: PlcTwin) -> None:
        self.rmap, self.twin = rmap, twin
        twin.use_modbus = True
        # another page window models a PLC program built with that GVL_CompTableParam.WINDOW_LREALS
        twin.runtime.set_constant("GVL_CompTableParam.WINDOW_LREALS", rmap.window_lreals)
        self.image = twin.modbus_memory(rmap.area_size)
        self.window_writes = 0          # window writes since the last header write (fault points)

    def point(self, fc: int, off: int, count: int, values) -> Point | None:
        """Where in the transfer a request belongs (for fault injection)."""
        r = self.rmap
        if fc in _FC_READ:
            if off >= r.WINDOW or r.SHADOW_HEADER <= off < r.COMMIT_VERSION:
                return Point.AFTER_STAGE
            if r.STATE <= off < r.ACTIVE_HEADER:
                lo, hi = (int(w) for w in self.image[r.COMMIT_VERSION:r.COMMIT_VERSION + 2])
                committed = is_token(lo | hi << 16)            # low word first
                return Point.ACK_WAIT if committed else Point.BEFORE_STAGE
            return Point.BEFORE_STAGE if off < r.SHADOW_HEADER else None
        if off == r.SHADOW_HEADER:
            self.window_writes = 0
            return None
        if off >= r.WINDOW:
            self.window_writes += 1
            return Point.MID_STAGE if self.window_writes > 1 else None
        if off == r.COMMIT_VERSION:
            words = list(values or ()) + [0, 0]
            return Point.COMMIT if is_token(words[0] | words[1] << 16) else Point.BEFORE_STAGE
        return None


def _tf6250_exception(request: bytes, reply: bytes) -> bytes:
    """pymodbus' server answers a request it cannot decode with function 0x80, exception 1. TF6250 (as
    the Modbus application protocol, sections 6.3 and 6.12) answers a quantity outside 1..125 (FC3/FC4)
    or 1..123 (FC16) with the request's function | 0x80 and exception 3, ILLEGAL DATA VALUE."""
    if len(reply) < 9 or reply[7] != 0x80 or reply[8] != 1 or len(request) < 12:
        return reply
    fc = request[7]
    count = int.from_bytes(request[10:12], "big")
    limit = {3: FC3_MAX, 4: FC3_MAX, 16: FC16_MAX}.get(fc)
    if limit is None or 1 <= count <= limit:
        return reply
    return reply[:7] + bytes([fc | 0x80, 3])


class ModbusMockPlc(MockPlc):
    """A mock PLC serving ST_CompTableModbusArea over Modbus TCP on 127.0.0.1.

    ``with ModbusMockPlc() as plc: push(ModbusLink(plc.host, plc.port), table)``
    """

    transport = "modbus"

    def __init__(self, *args, rmap: ModbusMap = ModbusMap(), **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.rmap = rmap
        self.area = ModbusArea(rmap, self.twin)
        self._mute = 0
        self._last_rx = b""
        self._server: ModbusTcpServer | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None

    @property
    def target(self) -> str:
        return f"{self.host}:{self.port}"

    def _reset_volatile(self) -> None:
        self.area = ModbusArea(self.rmap, self.twin)        # %M is not persistent

    def _device(self) -> SimDevice:
        """Holding registers of the whole mapped area (TF6250: 16#3000..16#5FFF -> %MB0..), all writable.

        TF6250 maps holding registers onto PLC memory without any notion of who owns a variable, so
        a write to a register the PLC writes is accepted; the PLC overwrites it at the end of its next
        cycle (FB_CompTableModbus.M_CopyOut). The bridge itself only writes its allow-list (:class:`ModbusLink`).
        """
        r = self.rmap
        simdata = [SimData(address=r.base, count=r.area_size, values=0, datatype=DataType.REGISTERS,
                           readonly=False)]
        return SimDevice(id=r.device_id, simdata=simdata, action=self._action)

    async def _action(self, fc: int, start: int, address: int, count: int, registers: list[int], values):
        """SimDevice hook for every access: faults, then the register image of the area."""
        off = address - self.rmap.base
        at = address - start
        if self.booting():          # TF6250 runs, the PLC runtime does not yet: its ADS access fails
            return ExcCodes.DEVICE_FAILURE
        if fc not in FC_HOLDING:    # another Modbus area (this PLC has no I/O image there), or no TF6250 function
            return ExcCodes.ILLEGAL_ADDRESS if fc in TF6250_FUNCTIONS else ExcCodes.ILLEGAL_FUNCTION
        self.count(write=values is not None)
        with self.twin.lock:
            point = self.area.point(fc, off, count, values)
        fault = self.faults.trigger(point) if point is not None else None
        corrupt = False
        if fault is not None:
            await asyncio.sleep(fault.wait_s)
            if fault.kind == Kind.NO_REPLY:
                self._mute += 1
                return ExcCodes.DEVICE_FAILURE
            elif fault.kind == Kind.DROP:
                for conn in list(self._server.active_connections.values()):
                    conn.close()
                return ExcCodes.DEVICE_FAILURE
            elif fault.kind == Kind.ERROR:
                return ExcCodes(fault.code or ExcCodes.DEVICE_FAILURE)
            elif fault.kind == Kind.BUSY:
                return ExcCodes.DEVICE_BUSY
            elif fault.kind == Kind.CORRUPT and point == Point.COMMIT:
                self.twin.corrupt_shadow()
            else:
                corrupt = fault.kind == Kind.CORRUPT
        with self.twin.lock:
            if values is None:
                registers[at:at + count] = self.area.image[off:off + count].tolist()
                if corrupt:
                    registers[at] ^= 0x0001
            else:
                if corrupt:
                    values[0] ^= 0x0001
                self.area.image[off:off + count] = values
        return None

    def _trace(self, sending: bool, data: bytes) -> bytes:
        """Swallow the reply of a request that hit a no_reply fault; TF6250's exception codes."""
        if not sending:
            self._last_rx = bytes(data)
            return data
        if self._mute:
            self._mute -= 1
            return b""
        return _tf6250_exception(self._last_rx, data)

    def _start_server(self) -> None:
        ready = threading.Event()
        failure: list[BaseException] = []

        async def serve() -> None:
            self._loop = asyncio.get_running_loop()
            self._server = ModbusTcpServer(self._device(), address=(self.host, self.port), trace_packet=self._trace)
            await self._server.serve_forever(background=True)
            self.port = self._server.transport.sockets[0].getsockname()[1]
            ready.set()
            try:
                await asyncio.wait_for(asyncio.shield(self._server.serving),
                                       timeout=max(0.0, self.deadline - time.monotonic()))
            except asyncio.TimeoutError:
                pass
            await self._server.shutdown()

        def run() -> None:
            try:
                asyncio.run(serve())
            except BaseException as exc:   # reported to the starting thread
                failure.append(exc)
                ready.set()

        self._thread = threading.Thread(target=run, name="modbus-mock", daemon=True)
        self._thread.start()
        if not ready.wait(10.0) or failure:
            raise RuntimeError(f"Modbus mock PLC did not start: {failure[0] if failure else 'time-out'}")

    def _stop_server(self) -> None:
        if self._server is not None and self._loop is not None and self._loop.is_running():
            try:
                asyncio.run_coroutine_threadsafe(self._server.shutdown(), self._loop).result(5.0)
            except (RuntimeError, TimeoutError, asyncio.CancelledError):
                pass
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        self._server = self._loop = self._thread = None
