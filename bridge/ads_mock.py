"""A mock TwinCAT PLC over ADS: ``pyads.testserver`` with correct AMS/TCP framing and a strict handler.

Differences from the stock test server, all as a real PLC behaves:

- every request is read as one whole AMS/TCP frame (6-byte header, then exactly the announced length;
  the stock server reads ``recvfrom(4096)`` and truncates larger writes);
- reads and writes of a symbol must have the symbol's exact size, else ADS error 1797; unknown
  symbol names and handles answer 1808; sum commands answer 1793 (not used by the bridge); writes
  to PLC-owned symbols answer 1796;
- the symbols are GVL_CompTable's, backed by a :class:`pmcal.bridge.plc_twin.PlcTwin` running its task;
- fault injection per :mod:`pmcal.bridge.faults`; ``ads_state`` can be set to STOP.

Each mock has its own AMS NetID (two endpoints with one NetID in one process fail with error 1286).
"""

from __future__ import annotations

import os
import select
import socket
import struct
import threading
import time

from pyads import constants
from pyads.testserver import AdsTestServer, AdvancedHandler, PLCVariable
from pyads.testserver.handler import AmsPacket, AmsResponseData
from pyads.testserver.testserver import AdsClientConnection

from pmcal.bridge.ads_map import AdsMap, AdsTarget
from pmcal.bridge.faults import Kind, Point
from pmcal.bridge.mock import LOOPBACK, MockPlc
from pmcal.bridge.plc_types import SYMBOLS, Symbol

_NO_REPLY = "no-reply"
_DROP = "drop"
ERR_TARGET_PORT_NOT_FOUND = 6        # AMS router: no ADS server on that port of this NetID
ERR_TARGET_MACHINE_NOT_FOUND = 7     # AMS router: no route to that NetID
ERR_SERVICE_NOT_SUPPORTED = 1793
ERR_INVALID_GROUP = 1794
ERR_ACCESS_DENIED = 1796
ERR_INVALID_SIZE = 1797
ERR_SYMBOL_NOT_FOUND = 1808
_ADS_TYPES = {"UINT": constants.ADST_UINT16, "UDINT": constants.ADST_UINT32}


class TwinVariable(PLCVariable):
    """A GVL_CompTable symbol whose value lives in the PLC twin."""

    def __init__(self, name: str, sym: Symbol, mock: "AdsMockPlc") -> None:
        self._mock, self._sym, self._ready = mock, sym, False
        ads_type = _ADS_TYPES.get(sym.st_type, constants.ADST_REAL64 if "LREAL" in sym.st_type
                                  else constants.ADST_BIGTYPE)
        super().__init__(name, bytes(sym.size), ads_type, sym.st_type)
        self._ready = True

    @property
    def value(self) -> bytes:
        return self._mock.twin.read_symbol(self._sym.key)

    @value.setter
    def value(self, data: bytes) -> None:
        if self._ready:
            self._mock.twin.write_symbol(self._sym.key, data)

    @property
    def sym(self) -> Symbol:
        return self._sym

    @property
    def size(self) -> int:
        """The declared size (what symbol information reports)."""
        return self._sym.size


class StrictHandler(AdvancedHandler):
    """AdvancedHandler over the twin's symbols, strict about sizes and names, with faults."""

    def __init__(self, mock: "AdsMockPlc") -> None:
        super().__init__()
        self.mock = mock
        for sym in mock.symbols:
            self.add_variable(TwinVariable(mock.amap.name(sym.key), sym, mock))

    def handle_request(self, request: AmsPacket):
        h = request.ams_header
        routing = self._routing_error(h)
        if routing:
            # as the TwinCAT router: the AMS header's error field, no ADS payload
            return AmsResponseData(struct.pack("<H", struct.unpack("<H", h.state_flags)[0] | 0x0001),
                                   struct.pack("<I", routing), b"")
        cmd = struct.unpack("<H", h.command_id)[0]
        data = h.data
        var, code, point, group = None, 0, Point.BEFORE_STAGE, 0
        if cmd in (constants.ADSCOMMAND_READ, constants.ADSCOMMAND_WRITE, constants.ADSCOMMAND_READWRITE):
            group, offset = struct.unpack("<II", data[:8])
            var, code = self._resolve(cmd, group, offset, data)
            point = self._point(cmd, group, var, data)
        elif cmd != constants.ADSCOMMAND_READSTATE:
            return super().handle_request(request)
        self.mock.count(write=cmd == constants.ADSCOMMAND_WRITE and group == constants.ADSIGRP_SYM_VALBYHND)
        fault = self.mock.faults.trigger(point) if point is not None else None
        corrupt = False
        if fault is not None:
            time.sleep(fault.wait_s)
            if fault.kind == Kind.NO_REPLY:
                return _NO_REPLY
            elif fault.kind == Kind.DROP:
                return _DROP
            elif fault.kind == Kind.ERROR:
                return _error(request, cmd, fault.code or ERR_ACCESS_DENIED)
            elif fault.kind == Kind.CORRUPT and point == Point.COMMIT:
                self.mock.twin.corrupt_shadow()
            elif fault.kind == Kind.CORRUPT and cmd == constants.ADSCOMMAND_WRITE:
                request = request._replace(ams_header=h._replace(data=_flip(data, 12)))
            else:
                corrupt = fault.kind == Kind.CORRUPT
        if cmd == constants.ADSCOMMAND_READSTATE:
            response = _reply(request, struct.pack("<IHH", 0, self.mock.ads_state, 0))
        elif code:
            return _error(request, cmd, code)
        elif var is not None and cmd == constants.ADSCOMMAND_READ:      # value access, sizes checked
            value = var.value
            response = _reply(request, struct.pack("<II", 0, len(value)) + value)
        elif var is not None and cmd == constants.ADSCOMMAND_WRITE:
            var.value = request.ams_header.data[12:]
            response = _reply(request, struct.pack("<I", 0))
        else:                                                          # handles, symbol information
            try:
                response = super().handle_request(request)
            except KeyError:
                return _error(request, cmd, ERR_SYMBOL_NOT_FOUND)
        if corrupt:           # first payload byte after the result (and length) fields
            response = response._replace(data=_flip(response.data, 4 if cmd == constants.ADSCOMMAND_READSTATE else 8))
        return response

    def _routing_error(self, h) -> int:
        """0, or the AMS error a TwinCAT router returns for a packet not addressed to this PLC runtime:
        ``ERR_TARGETMACHINENOTFOUND`` (7) for another AMS NetID, ``ERR_TARGETPORTNOTFOUND`` (6) for a
        port with no ADS server on this NetID (Beckhoff InfoSys, "ADS Return Codes", codes 0x6 and 0x7;
        pyads.errorcodes)."""
        netid = ".".join(str(b) for b in h.target_net_id)
        if netid != self.mock.netid:
            return ERR_TARGET_MACHINE_NOT_FOUND
        if struct.unpack("<H", h.target_port)[0] != self.mock.amap.ams_port:
            return ERR_TARGET_PORT_NOT_FOUND
        return 0

    def _resolve(self, cmd: int, group: int, offset: int, data: bytes) -> tuple[TwinVariable | None, int]:
        """The variable a request addresses and the ADS error it earns (0: none)."""
        if group in (constants.ADSIGRP_SUMUP_READ, constants.ADSIGRP_SUMUP_WRITE):
            return None, ERR_SERVICE_NOT_SUPPORTED
        if cmd == constants.ADSCOMMAND_READWRITE and group in (constants.ADSIGRP_SYM_HNDBYNAME,
                                                               constants.ADSIGRP_SYM_INFOBYNAMEEX):
            wlen = struct.unpack("<I", data[12:16])[0]
            name = data[16:16 + wlen].split(b"\0", 1)[0].decode("utf-8", "replace")
            var = next((v for v in self._data.values() if v.name == name), None)
            return var, 0 if var is not None else ERR_SYMBOL_NOT_FOUND
        if group == constants.ADSIGRP_SYM_RELEASEHND:
            return None, 0
        if group == constants.ADSIGRP_SYM_VALBYHND:
            var = next((v for v in self._data.values() if v.handle == offset), None)
        else:
            var = self._data.get((group, offset))
        if var is None:
            return None, ERR_SYMBOL_NOT_FOUND if group == constants.ADSIGRP_SYM_VALBYHND else ERR_INVALID_GROUP
        if cmd == constants.ADSCOMMAND_READWRITE:
            return var, ERR_SERVICE_NOT_SUPPORTED
        length = struct.unpack("<I", data[8:12])[0]
        if length != var.sym.size or (cmd == constants.ADSCOMMAND_WRITE and len(data) - 12 != length):
            return var, ERR_INVALID_SIZE
        if cmd == constants.ADSCOMMAND_WRITE and var.sym.written_by != "bridge":
            return var, ERR_ACCESS_DENIED
        return var, 0

    def _point(self, cmd: int, group: int, var: TwinVariable | None, data: bytes) -> Point | None:
        """Where in the transfer this request belongs (for fault injection)."""
        if var is None or group != constants.ADSIGRP_SYM_VALBYHND:
            return Point.BEFORE_STAGE          # symbol look-ups, handles
        key = var.sym.key
        if cmd == constants.ADSCOMMAND_WRITE:
            if key == "shadow":
                return Point.MID_STAGE
            if key == "commit":
                return Point.COMMIT if any(data[12:16]) else Point.BEFORE_STAGE
            return None
        if key in ("shadow", "shadow_header"):
            return Point.AFTER_STAGE
        if key == "state":
            return Point.ACK_WAIT if self.mock.twin.commit_token else Point.BEFORE_STAGE
        return None if key.startswith("lookup") else Point.BEFORE_STAGE


def _reply(request: AmsPacket, data: bytes) -> AmsResponseData:
    state = struct.unpack("<H", request.ams_header.state_flags)[0] | 0x0001
    return AmsResponseData(struct.pack("<H", state), b"\0\0\0\0", data)


def _error(request: AmsPacket, cmd: int, code: int) -> AmsResponseData:
    """An ADS response carrying ``code`` in its result field (and an empty payload)."""
    tail = b"" if cmd == constants.ADSCOMMAND_WRITE else b"\0\0\0\0"
    return _reply(request, struct.pack("<I", code) + tail)


def _flip(data: bytes, pos: int) -> bytes:
    """``data`` with the lowest bit of byte ``pos`` flipped (if there is such a byte)."""
    if pos >= len(data):
        return data
    return data[:pos] + bytes([data[pos] ^ 0x01]) + data[pos + 1:]


class _FramedConnection(AdsClientConnection):
    """One client connection: whole AMS/TCP frames in, one response (or a fault) out."""

    def _recv_exact(self, n: int) -> bytes | None:
        buf = bytearray()
        while len(buf) < n:
            try:
                chunk = self.client.recv(n - len(buf))
            except OSError:
                return None
            if not chunk:
                return None
            buf += chunk
        return bytes(buf)

    def run(self) -> None:
        mock = self.server.mock
        while self._run and not mock.expired():
            try:
                ready, _, _ = select.select([self.client], [], [], 0.05)
            except (OSError, ValueError):
                break
            if not ready:
                continue
            head = self._recv_exact(6)
            body = self._recv_exact(struct.unpack("<I", head[2:6])[0]) if head else None
            if body is None or len(body) < 32:
                break
            request = self.construct_request(head + body)
            response = self.handler.handle_request(request)
            if response == _DROP:
                break
            if response == _NO_REPLY:
                continue
            try:
                self.client.sendall(self.construct_response(response, request))
            except OSError:
                break
        self._run = False
        try:
            self.client.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.client.close()

    def stop(self) -> None:
        self._run = False
        if threading.current_thread() is not self:
            self.join(timeout=5.0)


class _FramedServer(AdsTestServer):
    """AdsTestServer that hands connections to :class:`_FramedConnection` and ends at the deadline."""

    def __init__(self, mock: "AdsMockPlc") -> None:
        self.mock = mock
        super().__init__(handler=StrictHandler(mock), ip_address=LOOPBACK, port=mock.port, logging=False)

    def run(self) -> None:
        self._run = True
        self.server.listen(5)
        while self._run and not self.mock.expired():
            try:
                ready, _, _ = select.select([self.server], [], [], 0.05)
                if not ready:
                    continue
                client, address = self.server.accept()
            except (OSError, ValueError):
                continue
            conn = _FramedConnection(handler=self.handler, client=client, address=address, server=self)
            conn.daemon = True
            conn.start()
            self.clients = [c for c in self.clients if c.is_alive()] + [conn]
        self._run = False


class AdsMockPlc(MockPlc):
    """A mock PLC serving GVL_CompTable over ADS on 127.0.0.1 (ephemeral port by default).

    ``with AdsMockPlc() as plc: push(AdsLink(AdsTarget.parse(plc.target)), table)``
    """

    transport = "ads"

    def __init__(self, *args, amap: AdsMap = AdsMap(), symbols: tuple[Symbol, ...] = SYMBOLS, **kwargs) -> None:
        """``symbols``: the GVL as this PLC program declares it (another one models an old program)."""
        super().__init__(*args, **kwargs)
        self.amap = amap
        self.symbols = symbols
        self.ads_state = constants.ADSSTATE_RUN
        self._server: _FramedServer | None = None

    @property
    def netid(self) -> str:
        """An AMS NetID of its own, derived from the process and the port."""
        return f"10.{os.getpid() % 250 + 1}.{self.port >> 8}.{self.port & 0xFF}.1.1"

    @property
    def address(self) -> AdsTarget:
        return AdsTarget(self.netid, self.host, self.port)

    @property
    def target(self) -> str:
        return str(self.address)

    def _start_server(self) -> None:
        self._server = _FramedServer(self)
        self._server.server.listen(5)            # accept connections as soon as this returns (restart)
        self.port = self._server.server.getsockname()[1]
        self._server.start()

    def _stop_server(self) -> None:
        server, self._server = self._server, None
        if server is not None:
            server.close()
            server.join(timeout=5.0)
