"""Modbus TCP client (pymodbus) for the compensation-table area: a thin typed PlcLink.

The register map and the paged window are described in :mod:`pmcal.bridge.modbus_map`. Writes are limited
to the register ranges of an allow-list (default: header, commit, page control and window). The sync
client is used without its own retries: a time-out or a dropped connection is a
:class:`pmcal.bridge.errors.LinkError` and :func:`pmcal.bridge.transfer.push` reopens and restarts the transfer;
a Modbus exception response is the PLC refusing a request (:class:`pmcal.bridge.errors.DeviceError`).
"""

from __future__ import annotations

import re
import time

from pymodbus.client import ModbusTcpClient
from pymodbus.exceptions import ModbusException

from pmcal.bridge.errors import AckTimeout, DeviceError, InterfaceError, LinkError, WriteNotAllowed
from pmcal.bridge.link import LinkBase
from pmcal.bridge.modbus_map import (MAGIC, PAGE_LOAD, PAGE_OK, PAGE_STORE, ModbusMap, from_registers,
                               to_registers)
from pmcal.bridge.comptable import NAXES_MAX, NMOTOR_MAX, NVALUES_MAX
from pmcal.bridge.plc_types import HOST_PATTERN, INTERFACE_VERSION, LREAL_SIZE, PUSH_WRITES

MODBUS_TCP_PORT = 502


def parse_host_port(text: str, default_port: int = MODBUS_TCP_PORT) -> tuple[str, int]:
    """``HOST[:PORT]`` -> (host, port); ValueError if malformed."""
    m = re.fullmatch(rf"({HOST_PATTERN})(?::(\d{{1,5}}))?", text.strip(), flags=re.ASCII)
    host, port = (m[1], m[2] or str(default_port)) if m else ("", "")
    if not host or not 0 < int(port) < 65536:
        raise ValueError(f"Modbus target {text!r}: expected HOST[:PORT]")
    return host, int(port)


class ModbusLink(LinkBase):
    """One Modbus TCP connection to ST_CompTableModbusArea. ``writes``: symbol keys it may write."""

    transport = "modbus"

    def __init__(self, host: str, port: int = MODBUS_TCP_PORT, *, rmap: ModbusMap = ModbusMap(),
                 writes: frozenset[str] = PUSH_WRITES, timeout_s: float = 1.0, page_timeout_s: float = 1.0,
                 poll_s: float = 0.0005) -> None:
        self.host, self.port, self.rmap = host, int(port), rmap
        self.writes = frozenset(writes)
        self._allowed = rmap.writable(self.writes)
        self.timeout_s, self.page_timeout_s, self.poll_s = timeout_s, page_timeout_s, poll_s
        self.target = f"{host}:{self.port}"
        self._client: ModbusTcpClient | None = None

    # ---- connection -----------------------------------------------------------------------
    def open(self) -> None:
        if self._client is not None:
            return
        client = ModbusTcpClient(self.host, port=self.port, timeout=self.timeout_s, retries=0)
        if not client.connect():
            client.close()
            raise LinkError(f"Modbus connection to {self.target} failed (refused or unreachable)")
        self._client = client

    def close(self) -> None:
        client, self._client = self._client, None
        if client is not None:
            client.close()

    # ---- interface --------------------------------------------------------------------------
    def check_interface(self) -> None:
        """Magic, interface version, array sizes and window as expected; the PLC task is cycling."""
        r = self.rmap
        info = self._read(r.MAGIC, 6)
        expect = [MAGIC, INTERFACE_VERSION, NVALUES_MAX, NMOTOR_MAX, r.window_lreals, NAXES_MAX]
        if info != expect:
            raise InterfaceError(f"Modbus area at {self.target} register {r.base} holds {info}, expected "
                                 f"{expect} (magic, interface version, NVALUES_MAX, NMOTOR_MAX, window, NAXES_MAX): "
                                 "PLC code or register map does not match")
        first = self.read_state().cycle
        deadline = time.monotonic() + self.page_timeout_s
        while self.read_state().cycle == first:
            if time.monotonic() >= deadline:
                raise InterfaceError(f"PLC at {self.target} is not running (cycle counter stands at {first})")
            time.sleep(self.poll_s)

    def read_symbol(self, key: str) -> bytes:
        return from_registers(self._read(self.rmap.offset(key), self.rmap.size(key)))

    def write_symbol(self, key: str, data: bytes) -> None:
        regs = to_registers(data)
        if len(regs) != self.rmap.size(key):
            raise WriteNotAllowed(f"refusing to write {len(data)} bytes to {key} ({self.rmap.size(key)} registers)")
        self._write(self.rmap.offset(key), regs)

    # ---- the table through the paged window ---------------------------------------------
    def stage(self, header: bytes, rows: bytes) -> tuple[bytes, bytes]:
        """Header, then ``rows`` page by page (window writes, page control, PLC echo)."""
        self.write_symbol("shadow_header", header)
        regs = to_registers(rows)
        seq = self._page_seq()
        for page, count in self.rmap.pages(len(rows) // LREAL_SIZE):
            start = page * self.rmap.window_lreals * 4
            chunk = regs[start:start + 4 * count]
            for k in range(0, len(chunk), self.rmap.chunk):
                self._write(self.rmap.WINDOW + k, chunk[k:k + self.rmap.chunk])
            seq = self._page(page, count, PAGE_STORE, seq)
        return header, rows

    def read_back(self, data_size: int) -> tuple[bytes, bytes]:
        header = self.read_symbol("shadow_header")
        out: list[int] = []
        seq = self._page_seq()
        for page, count in self.rmap.pages(data_size // LREAL_SIZE):
            seq = self._page(page, count, PAGE_LOAD, seq)
            n = 4 * count
            for k in range(0, n, self.rmap.read_chunk):
                out += self._read(self.rmap.WINDOW + k, min(self.rmap.read_chunk, n - k))
        return header, from_registers(out)

    def _page_seq(self) -> int:
        return self._read(self.rmap.PAGE_ACK, 1)[0]

    def _page(self, page: int, count: int, cmd: int, seq: int) -> int:
        """Hand one page to the PLC and wait for its echo; returns the sequence number used."""
        seq = (seq + 1) & 0xFFFF or 1
        self._write(self.rmap.PAGE_CONTROL, [page, count, cmd, seq])
        deadline = time.monotonic() + self.page_timeout_s
        while True:
            done, status = self._read(self.rmap.PAGE_ACK, 2)
            if done == seq:
                if status != PAGE_OK:
                    raise DeviceError(f"PLC at {self.target} refused page {page} ({count} LREAL): status {status}")
                return seq
            if time.monotonic() >= deadline:
                raise AckTimeout(f"PLC at {self.target} did not take page {page} within {self.page_timeout_s:g} s")
            time.sleep(self.poll_s)

    # ---- registers ----------------------------------------------------------------------------
    def _conn(self) -> ModbusTcpClient:
        if self._client is None:
            raise LinkError(f"Modbus link to {self.target} is not open")
        return self._client

    def _read(self, offset: int, count: int) -> list[int]:
        addr = self.rmap.base + offset
        rr = self._call(f"read registers {addr}..{addr + count - 1}", self._conn().read_holding_registers,
                        addr, count=count, device_id=self.rmap.device_id)
        if len(rr.registers) != count:
            raise LinkError(f"Modbus read of {count} registers at {addr} from {self.target} returned "
                            f"{len(rr.registers)}")
        return list(rr.registers)

    def _write(self, offset: int, regs: list[int]) -> None:
        if not any(offset in r and offset + len(regs) - 1 in r for r in self._allowed):
            raise WriteNotAllowed(f"refusing to write registers {self.rmap.base + offset}.."
                                  f"{self.rmap.base + offset + len(regs) - 1}: not in this client's allow-list")
        # FC16 carries at most 123 registers: a format-4 header (124) goes in two requests
        for k in range(0, len(regs), self.rmap.chunk):
            addr = self.rmap.base + offset + k
            part = regs[k:k + self.rmap.chunk]
            self._call(f"write registers {addr}..{addr + len(part) - 1}", self._conn().write_registers,
                       addr, part, device_id=self.rmap.device_id)

    def _call(self, what: str, fn, *args, **kwargs):
        """Run a pymodbus request: exceptions -> LinkError, exception responses -> DeviceError."""
        try:
            rr = fn(*args, **kwargs)
        except (ModbusException, OSError) as exc:
            self.close()
            raise LinkError(f"Modbus link to {self.target} failed to {what}: {_one_line(exc)}") from None
        if rr.isError():
            code = getattr(rr, "exception_code", None)
            raise DeviceError(f"PLC at {self.target} refused to {what}: Modbus exception {code}")
        return rr


def _one_line(exc: Exception) -> str:
    return " ".join(str(exc).split())[:200]
