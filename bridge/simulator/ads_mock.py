"""A mock TwinCAT 3 PLC over ADS, as strict as the real runtime: ``pyads.testserver`` framing, our own handler.

What it serves, as a TwinCAT 3.1 PLC runtime on AMS port 851 does (codes: Beckhoff InfoSys "ADS Return
Codes", texts as in ``pyads.errorcodes``):

- **Memory.** GVL_CompTable's visible variables lie in the PLC data area, index group 16#4040, in
  declaration order with natural alignment (symbol information reports group and offset, as TwinCAT
  does, so pyads' ``read_list_by_name``/``write_list_by_name`` work). Any read or write inside the area
  is accepted, partial ones too (a few LREALs into ``aShadow`` by offset, several variables at once);
  outside it: 0x703 invalid offset / 0x705 invalid size; another index group: 0x702.
- **Symbols and handles.** 16#F003 handle by name, 16#F005 value by handle, 16#F006 release, 16#F004
  value by name, 16#F009 symbol information, 16#F00B/F00C/F00F the symbol table upload. Names are case-insensitive; an array element
  (``GVL_CompTable.aShadow[3,0,1]``) is a symbol of its own. Unknown names, unknown or released handles:
  0x710 symbol not found. Struct members (``GVL_CompTable.stState.nCycle``) are symbols too, laid out
  from the shipped DUTs. By handle, as on TwinCAT, a read returns at most the symbol's bytes and a
  shorter write changes only its first bytes (a zero-length write nothing); a longer write: 0x705.
  Handles live until released or until the PLC restarts (then 0x710).
- **Sum commands** (16#F080 read, 16#F081 write, 16#F082 read-write, 16#F083 read-ex) with one
  result code per sub-request, a failed sub-request leaving the others done.
- **Device notifications** (AddDeviceNotification / DeleteDeviceNotification): the server sends
  DeviceNotification frames on change (checked every cycle time, at least the PLC task cycle) or
  cyclically, the first one at once; 0x713 for another transmission mode, 0x714 for an unknown handle.
  They end with the connection.
- **Routes.** Frames from an AMS NetID without a route (``routes``) are dropped by the router without
  an answer: the client times out (pyads 1861). Another target NetID: AMS error 7; another AMS port,
  or port 851 while the runtime boots: 6.
- **PLC state.** ``read_state`` answers RUN, or STOP after :meth:`AdsMockPlc.stop_plc` or an ADS
  WriteControl to STOP (the task does not run; variables stay readable and writable, as on TwinCAT);
  WriteControl RUN starts it again.
- **Write protection** only where the GVL declares it (``{attribute 'symbol' := 'read'}``: 0x704).
  Otherwise a write to a PLC-owned variable is accepted, as TwinCAT does, and lasts until the PLC
  task next writes it (its next cycle).
- fault injection per :mod:`pmcal.bridge.simulator.faults` (including ``busy``: 0x708 device busy).
- the task behind it is the ST of plc/ itself, interpreted cycle by cycle
  (:class:`pmcal.bridge.simulator.plc_runtime.PlcTwin`); a trapped FPU exception stops the PLC (ADS state STOP).

Each mock has its own AMS NetID (two endpoints with one NetID in one process fail with error 1286).
"""

from __future__ import annotations

import os
import re
import select
import socket
import struct
import threading
import time
import uuid
from dataclasses import dataclass, field

from pyads import constants
from pyads.testserver import AdsTestServer
from pyads.testserver.handler import AbstractHandler, AmsPacket, AmsResponseData
from pyads.testserver.testserver import AdsClientConnection

from pmcal.bridge.ads_map import AdsMap, AdsTarget, read_only_symbols, struct_members
from pmcal.bridge.simulator.faults import Kind, Point
from pmcal.bridge.simulator.mock import LOOPBACK, MockPlc
from pmcal.bridge.plc_types import SYMBOLS, Symbol, is_token

_NO_REPLY = "no-reply"
_DROP = "drop"
#: TwinCAT 3 PLC data area (the index group of GVL symbols in the symbol information)
IG_PLC_DATA = 0x4040
IG_SUMUP_READWRITE = 0xF082
IG_SUMUP_READEX = 0xF083
ERR_TARGET_PORT_NOT_FOUND = 6        # AMS router: no ADS server on that port of this NetID
ERR_TARGET_MACHINE_NOT_FOUND = 7     # AMS router: no route to that NetID
ERR_SERVICE_NOT_SUPPORTED = 0x701
ERR_INVALID_GROUP = 0x702
ERR_INVALID_OFFSET = 0x703
ERR_ACCESS_DENIED = 0x704            # reading/writing not permitted
ERR_INVALID_SIZE = 0x705
ERR_INVALID_PARAM = 0x706
ERR_NOT_READY = 0x707
ERR_BUSY = 0x708
ERR_SYMBOL_NOT_FOUND = 0x710
ERR_TRANSMODE_NOT_SUPPORTED = 0x713
ERR_NOTIFY_HANDLE_INVALID = 0x714
ERR_NOTIFY_SIZE_TOO_BIG = 0x717
_ADS_TYPES = {"UINT": constants.ADST_UINT16, "UDINT": constants.ADST_UINT32, "WORD": constants.ADST_UINT16,
              "INT": constants.ADST_INT16, "LREAL": constants.ADST_REAL64}
_NOTIFY_MODES = (constants.ADSTRANS_SERVERCYCLE, constants.ADSTRANS_SERVERONCHA)
_UPLOAD_GROUPS = (constants.ADSIGRP_SYM_UPLOAD, constants.ADSIGRP_SYM_UPLOADINFO, constants.ADSIGRP_SYM_UPLOADINFO2)
_FILETIME_EPOCH = 11644473600          # s from 1601-01-01 to 1970-01-01


@dataclass(frozen=True)
class Region:
    """A named piece of the PLC data area: a whole variable or one array element."""

    name: str
    sym: Symbol
    offset: int                 # in the data area, bytes
    size: int
    st_type: str = ""           # the PLC type of a part (array element, struct member)

    @property
    def whole(self) -> bool:
        return self.size == self.sym.size


class GvlArea:
    """The visible variables of GVL_CompTable laid out as TwinCAT 3 does in the PLC data area."""

    def __init__(self, amap: AdsMap, symbols: tuple[Symbol, ...]) -> None:
        self.amap = amap
        self.regions: list[Region] = []
        offset = 0
        for sym in symbols:
            align = 2 if sym.size == 2 else 4 if sym.size == 4 else 8
            offset = -(-offset // align) * align
            self.regions.append(Region(amap.name(sym.key), sym, offset, sym.size))
            offset += sym.size
        self.size = offset
        self._by_name = {r.name.casefold(): r for r in self.regions}

    def find(self, name: str) -> Region | None:
        """The region of a symbol name (case-insensitive): a variable, one of its struct members
        (``GVL_CompTable.stState.nCycle``, layouts from the shipped DUTs) or an array element
        (``name[i,j,k]``)."""
        name = name.strip().rstrip("\0").strip()
        m = re.fullmatch(r"(.+?)\s*\[([\d\s,]+)\]", name)
        key = (m[1] if m else name).casefold()
        base = self._by_name.get(key)
        if base is None and m is None:
            return self._member(name)
        if base is None or m is None:
            return base
        dims = _array_dims(base.sym.st_type)
        index = [int(x) for x in m[2].split(",")]
        if dims is None or len(index) != len(dims) or any(not lo <= i <= hi for i, (lo, hi) in zip(index, dims)):
            return None
        flat = 0
        for i, (lo, hi) in zip(index, dims):
            flat = flat * (hi - lo + 1) + (i - lo)
        return Region(f"{base.name}[{','.join(map(str, index))}]", base.sym, base.offset + 8 * flat, 8, "LREAL")

    def _member(self, name: str) -> Region | None:
        for region in self.regions:
            prefix = region.name.casefold() + "."
            if name.casefold().startswith(prefix):
                member = (struct_members(region.sym.st_type) or {}).get(name.casefold()[len(prefix):])
                if member is None:
                    return None
                offset, size, st_type = member
                return Region(name, region.sym, region.offset + offset, size, st_type)
        return None

    def spans(self, offset: int, size: int) -> list[tuple[Region, int, int, int]]:
        """(region, offset in the variable, offset in the buffer, bytes) of every variable the range touches."""
        out = []
        for r in self.regions:
            lo, hi = max(offset, r.offset), min(offset + size, r.offset + r.size)
            if lo < hi:
                out.append((r, lo - r.offset, lo - offset, hi - lo))
        return out

    def check(self, offset: int, size: int) -> int:
        """0, or the ADS error of an access to ``size`` bytes at ``offset`` of the data area."""
        if not 0 <= offset < self.size:
            return ERR_INVALID_OFFSET
        if size <= 0 or offset + size > self.size:
            return ERR_INVALID_SIZE
        return 0


def _array_dims(st_type: str) -> list[tuple[int, int]] | None:
    m = re.fullmatch(r"\s*ARRAY\s*\[(.*)\]\s*OF\s+LREAL\s*", st_type, re.I)
    if not m:
        return None
    return [tuple(int(v) for v in d.split("..")) for d in m[1].split(",")]


@dataclass
class Notification:
    """One device notification of one connection."""

    handle: int
    offset: int                 # in the data area
    size: int
    mode: int
    cycle_s: float
    reply_to: bytes             # the client's AMS NetID and port (6 + 2 bytes)
    due: float = 0.0
    last: bytes | None = None


@dataclass
class _Request:
    """One decoded ADS request: what it touches (for faults and the write counter)."""

    cmd: int
    group: int = 0
    offset: int = 0
    reads: list = field(default_factory=list)     # regions read
    writes: list = field(default_factory=list)    # (region, data) written


class StrictHandler(AbstractHandler):
    """The ADS server of the mock PLC runtime (see the module docstring)."""

    def __init__(self, mock: "AdsMockPlc") -> None:
        self.mock = mock
        self.area = mock.area

    # ---- dispatch ---------------------------------------------------------------------------
    def serve(self, request: AmsPacket, conn: "_FramedConnection"):
        """The response to ``request``, or ``_NO_REPLY`` / ``_DROP``."""
        h = request.ams_header
        source = ".".join(str(b) for b in h.source_net_id)
        if self.mock.routes is not None and source not in self.mock.routes:
            return _NO_REPLY               # the router has no route back: the frame is dropped
        routing = self._routing_error(h)
        if routing:                        # the router answers in the AMS header's error field
            return AmsResponseData(_state(request), struct.pack("<I", routing), b"")
        cmd = struct.unpack("<H", h.command_id)[0]
        data = bytes(h.data)
        req = _Request(cmd)
        if cmd in (constants.ADSCOMMAND_READ, constants.ADSCOMMAND_WRITE, constants.ADSCOMMAND_READWRITE) \
                and len(data) >= 12:
            req.group, req.offset = struct.unpack("<II", data[:8])
        point = self._point(req, data)
        fault = self.mock.faults.trigger(point) if point is not None else None
        if fault is not None:
            time.sleep(fault.wait_s)
            if fault.kind == Kind.NO_REPLY:
                return _NO_REPLY
            if fault.kind == Kind.DROP:
                return _DROP
            if fault.kind == Kind.ERROR:
                return _error(request, cmd, fault.code or ERR_ACCESS_DENIED)
            if fault.kind == Kind.BUSY:
                return _error(request, cmd, ERR_BUSY)
            if fault.kind == Kind.CORRUPT and point == Point.COMMIT:
                self.mock.twin.corrupt_shadow()
                fault = None
        corrupt = fault is not None and fault.kind == Kind.CORRUPT
        if cmd == constants.ADSCOMMAND_WRITECTRL:            # start / stop the PLC (outside the task's lock)
            code = self._write_control(data)
            return _error(request, cmd, code) if code else AmsResponseData(_state(request), b"\0" * 4, b"\0" * 4)
        with self.mock.twin.lock:
            payload = self._dispatch(cmd, data, req, conn, corrupt_write=corrupt)
        self.mock.count(write=bool(req.writes))
        if isinstance(payload, int):
            return _error(request, cmd, payload)
        if corrupt and req.reads:          # the first byte of the (last) value read
            payload = _flip(payload, len(payload) - req.reads[-1].size)
        return AmsResponseData(_state(request), b"\0\0\0\0", payload)

    def _dispatch(self, cmd: int, data: bytes, req: _Request, conn, corrupt_write: bool):
        """The response payload (bytes) or an ADS error code (int)."""
        if cmd == constants.ADSCOMMAND_READDEVICEINFO:
            return struct.pack("<IBBH16s", 0, 3, 1, 4024, b"Plc30 App")
        if cmd == constants.ADSCOMMAND_READSTATE:
            return struct.pack("<IHH", 0, self.mock.plc_state(), 0)
        if cmd == constants.ADSCOMMAND_ADDDEVICENOTE:
            return self._add_notification(data, conn)
        if cmd == constants.ADSCOMMAND_DELDEVICENOTE:
            handle = struct.unpack("<I", data[:4])[0] if len(data) >= 4 else 0
            return struct.pack("<I", 0) if conn.delete_notification(handle) else ERR_NOTIFY_HANDLE_INVALID
        if len(data) < 12:
            return ERR_INVALID_SIZE if cmd in (2, 3, 9) else ERR_SERVICE_NOT_SUPPORTED
        group, offset, length = struct.unpack("<III", data[:12])
        if cmd == constants.ADSCOMMAND_READ:
            err, value = self.read(group, offset, length, req)
            return err or struct.pack("<II", 0, len(value)) + value
        if cmd == constants.ADSCOMMAND_WRITE:
            value = data[12:12 + length]
            if corrupt_write and value:
                value = _flip(value, 0)
            if len(value) != length:
                return ERR_INVALID_SIZE
            return self.write(group, offset, value, req) or struct.pack("<I", 0)
        if cmd == constants.ADSCOMMAND_READWRITE:
            wlen = struct.unpack("<I", data[12:16])[0] if len(data) >= 16 else 0
            wdata = data[16:16 + wlen]
            if len(wdata) != wlen:
                return ERR_INVALID_SIZE
            err, value = self.read_write(group, offset, length, wdata, req, corrupt_write)
            return err or struct.pack("<II", 0, len(value)) + value
        return ERR_SERVICE_NOT_SUPPORTED

    def _write_control(self, data: bytes) -> int:
        """ADS WriteControl: STOP stops the PLC task, RUN (or RESET) starts it; other states 0x706."""
        state = struct.unpack("<H", data[:2])[0] if len(data) >= 2 else 0
        if state == constants.ADSSTATE_STOP:
            self.mock.stop_plc()
        elif state in (constants.ADSSTATE_RUN, constants.ADSSTATE_RESET):
            self.mock.start_plc()
        else:
            return ERR_INVALID_PARAM
        return 0

    # ---- the three services on one index group / offset ----------------------------------------
    def read(self, group: int, offset: int, length: int, req: _Request) -> tuple[int, bytes]:
        if group in _UPLOAD_GROUPS:                  # the symbol table (pyads get_all_symbols)
            out = self._upload(group)
            return (0, out) if length >= len(out) else (ERR_INVALID_SIZE, b"")
        region, err = self._target(group, offset, length)
        if err:
            return err, b""
        req.reads.append(region)
        return 0, self.mock.read_memory(region.offset, region.size)

    def write(self, group: int, offset: int, value: bytes, req: _Request) -> int:
        if group == constants.ADSIGRP_SYM_RELEASEHND:
            if len(value) != 4:
                return ERR_INVALID_SIZE
            return 0 if self.mock.handles.pop(struct.unpack("<I", value)[0], None) else ERR_SYMBOL_NOT_FOUND
        region, err = self._target(group, offset, len(value), write=True)
        if err:
            return err
        if region.size == 0:
            return 0
        if any(r.sym.st_name in self.mock.read_only for r, *_ in self.area.spans(region.offset, region.size)):
            return ERR_ACCESS_DENIED
        req.writes.append((region, value))
        self.mock.write_memory(region.offset, value)
        return 0

    def read_write(self, group: int, offset: int, rlen: int, wdata: bytes, req: _Request,
                   corrupt_write: bool = False) -> tuple[int, bytes]:
        if group in (constants.ADSIGRP_SYM_HNDBYNAME, constants.ADSIGRP_SYM_INFOBYNAMEEX,
                     constants.ADSIGRP_SYM_VALBYNAME):
            region = self.area.find(wdata.split(b"\0", 1)[0].decode("utf-8", "replace"))
            if region is None:
                return ERR_SYMBOL_NOT_FOUND, b""
            if group == constants.ADSIGRP_SYM_HNDBYNAME:
                out = struct.pack("<I", self.mock.new_handle(region))
            elif group == constants.ADSIGRP_SYM_INFOBYNAMEEX:
                out = _symbol_info(region)
            else:
                if rlen != region.size:
                    return ERR_INVALID_SIZE, b""
                req.reads.append(region)
                out = self.mock.read_memory(region.offset, region.size)
            if rlen < len(out):
                return ERR_INVALID_SIZE, b""
            return 0, out
        if group == constants.ADSIGRP_SUMUP_READ:
            return self._sum_read(offset, wdata, rlen, req, ex=False)
        if group == IG_SUMUP_READEX:
            return self._sum_read(offset, wdata, rlen, req, ex=True)
        if group == constants.ADSIGRP_SUMUP_WRITE:
            return self._sum_write(offset, wdata, rlen, req, corrupt_write)
        if group == IG_SUMUP_READWRITE:
            return self._sum_read_write(offset, wdata, rlen, req)
        if group == constants.ADSIGRP_SYM_VALBYHND:
            return ERR_SYMBOL_NOT_FOUND, b""        # TwinCAT: no ReadWrite on a value handle
        if group == IG_PLC_DATA:
            return ERR_SERVICE_NOT_SUPPORTED, b""
        return ERR_INVALID_GROUP, b""

    def _target(self, group: int, offset: int, length: int, write: bool = False) -> tuple[Region | None, int]:
        """The region a read/write addresses and the ADS error it earns (0: none)."""
        if group == constants.ADSIGRP_SYM_VALBYHND:
            region = self.mock.handles.get(offset)
            if region is None:
                return None, ERR_SYMBOL_NOT_FOUND
            if write and length > region.size:
                return None, ERR_INVALID_SIZE
            # TwinCAT serves the symbol's first bytes: a shorter write (a STRING, or pyads' zero-length
            # write of a 2-D array) changes only those, a read gets at most the symbol
            n = min(length, region.size)
            return Region(region.name, region.sym, region.offset, n, region.st_type), 0
        if group == IG_PLC_DATA:
            err = self.area.check(offset, length)
            if err:
                return None, err
            touched = self.area.spans(offset, length)
            first = touched[0][0] if touched else self.area.regions[0]
            whole = len(touched) == 1 and touched[0][1] == 0 and length == first.size
            return Region(first.name if whole else f"{IG_PLC_DATA:#x}:{offset}", first.sym, offset, length), 0
        return None, ERR_INVALID_GROUP

    def _upload(self, group: int) -> bytes:
        """16#F00B symbol upload (every visible variable), 16#F00C / 16#F00F its sizes."""
        entries = b"".join(_symbol_info(r) for r in self.area.regions)
        if group == constants.ADSIGRP_SYM_UPLOAD:
            return entries
        if group == constants.ADSIGRP_SYM_UPLOADINFO:
            return struct.pack("<II", len(self.area.regions), len(entries))
        return struct.pack("<6I", len(self.area.regions), len(entries), 0, 0, 0, 0)

    # ---- sum commands -------------------------------------------------------------------------
    def _sum_items(self, n: int, wdata: bytes, width: int) -> list[tuple] | None:
        if n == 0 or len(wdata) < n * width:
            return None
        return [struct.unpack_from("<" + "I" * (width // 4), wdata, k * width) for k in range(n)]

    def _sum_read(self, n: int, wdata: bytes, rlen: int, req: _Request, ex: bool) -> tuple[int, bytes]:
        items = self._sum_items(n, wdata, 12)
        if items is None or (not ex and rlen < 4 * n + sum(i[2] for i in items)):
            return ERR_INVALID_SIZE, b""
        codes, blobs = [], []
        for group, offset, size in items:
            err, value = self.read(group, offset, size, req)
            codes.append(struct.pack("<II", err, len(value)) if ex else struct.pack("<I", err))
            blobs.append(value if ex else (value + bytes(size))[:size])     # each item keeps its slot
        return 0, b"".join(codes) + b"".join(blobs)

    def _sum_write(self, n: int, wdata: bytes, rlen: int, req: _Request, corrupt: bool) -> tuple[int, bytes]:
        items = self._sum_items(n, wdata, 12)
        if items is None or len(wdata) != 12 * n + sum(i[2] for i in items) or rlen < 4 * n:
            return ERR_INVALID_SIZE, b""
        pos, codes = 12 * n, []
        for group, offset, size in items:
            value = wdata[pos:pos + size]
            pos += size
            if corrupt and size > 1000:          # the table payload of a staging write
                value, corrupt = _flip(value, 0), False
            codes.append(self.write(group, offset, value, req))
        return 0, struct.pack(f"<{n}I", *codes)

    def _sum_read_write(self, n: int, wdata: bytes, rlen: int, req: _Request) -> tuple[int, bytes]:
        items = self._sum_items(n, wdata, 16)
        if items is None or len(wdata) != 16 * n + sum(i[3] for i in items) or rlen < 8 * n + sum(
                i[2] for i in items):
            return ERR_INVALID_SIZE, b""
        pos, heads, blobs = 16 * n, [], []
        for group, offset, size, wsize in items:
            err, value = self.read_write(group, offset, size, wdata[pos:pos + wsize], req)
            pos += wsize
            heads.append(struct.pack("<II", err, len(value)))
            blobs.append(value)
        return 0, b"".join(heads) + b"".join(blobs)

    # ---- notifications ------------------------------------------------------------------------
    def _add_notification(self, data: bytes, conn) -> bytes | int:
        if len(data) < 24:
            return ERR_INVALID_SIZE
        group, offset, length, mode, _max_delay, cycle = struct.unpack("<6I", data[:24])
        if mode not in _NOTIFY_MODES:
            return ERR_TRANSMODE_NOT_SUPPORTED
        if group == constants.ADSIGRP_SYM_VALBYHND:
            region = self.mock.handles.get(offset)
            if region is None:
                return ERR_SYMBOL_NOT_FOUND
            if length > region.size:
                return ERR_NOTIFY_SIZE_TOO_BIG
            start = region.offset
        elif group == IG_PLC_DATA:
            err = self.area.check(offset, length)
            if err:
                return err
            start = offset
        else:
            return ERR_INVALID_GROUP
        if length == 0:
            return ERR_INVALID_SIZE
        cycle_s = max(cycle * 1e-7, self.mock.cycle_s)
        handle = conn.add_notification(Notification(0, start, length, mode, cycle_s, b""))
        return struct.pack("<II", 0, handle)

    # ---- routing and fault points ----------------------------------------------------------------
    def _routing_error(self, h) -> int:
        """0, or the AMS error a TwinCAT router returns for a packet it cannot deliver to this runtime:
        ``ERR_TARGETMACHINENOTFOUND`` (7) for another AMS NetID, ``ERR_TARGETPORTNOTFOUND`` (6) for a
        port with no ADS server on this NetID (and for port 851 while the runtime boots)."""
        netid = ".".join(str(b) for b in h.target_net_id)
        if netid != self.mock.netid:
            return ERR_TARGET_MACHINE_NOT_FOUND
        if struct.unpack("<H", h.target_port)[0] != self.mock.amap.ams_port or self.mock.booting():
            return ERR_TARGET_PORT_NOT_FOUND
        return 0

    def _point(self, req: _Request, data: bytes) -> Point | None:
        """Where in the transfer this request belongs (for fault injection), from the variables it touches."""
        keys_w, keys_r, commit_value = set(), set(), b""
        for group, offset, size, payload, write in _accesses(req.cmd, data):
            if group == constants.ADSIGRP_SYM_VALBYHND:
                region = self.mock.handles.get(offset)
                spans = [(region, 0, 0, region.size)] if region else []
            elif group == IG_PLC_DATA:
                spans = self.area.spans(offset, size)
            else:
                continue
            for region, _, pos, n in spans:
                (keys_w if write else keys_r).add(region.sym.key)
                if write and region.sym.key == "commit":
                    commit_value = payload[pos:pos + n]
        if "shadow" in keys_w:
            return Point.MID_STAGE
        if "commit" in keys_w:            # a token commits; 0 or NOT token withdraws or clears
            return Point.COMMIT if len(commit_value) == 4 and is_token(int.from_bytes(commit_value, "little")) \
                else Point.BEFORE_STAGE
        if keys_w:
            return None
        if keys_r & {"shadow", "shadow_header"}:
            return Point.AFTER_STAGE
        if "state" in keys_r:
            pending = is_token(int.from_bytes(self.mock.read_memory(*self.mock.location("commit")), "little"))
            return Point.ACK_WAIT if pending else Point.BEFORE_STAGE
        if keys_r and keys_r <= {"lookup_in", "lookup_out"}:
            return None
        return Point.BEFORE_STAGE


def _accesses(cmd: int, data: bytes):
    """(group, offset, size, payload, is_write) of every value access in a request, sum commands unrolled."""
    if len(data) < 12:
        return
    group, offset, length = struct.unpack("<III", data[:12])
    if cmd == constants.ADSCOMMAND_READ:
        yield group, offset, length, b"", False
    elif cmd == constants.ADSCOMMAND_WRITE:
        yield group, offset, length, data[12:], True
    elif cmd == constants.ADSCOMMAND_READWRITE and len(data) >= 16:
        w = data[16:]
        if group in (constants.ADSIGRP_SUMUP_READ, IG_SUMUP_READEX) and len(w) >= 12 * offset:
            for k in range(offset):
                g, o, s = struct.unpack_from("<III", w, 12 * k)
                yield g, o, s, b"", False
        elif group == constants.ADSIGRP_SUMUP_WRITE and len(w) >= 12 * offset:
            pos = 12 * offset
            for k in range(offset):
                g, o, s = struct.unpack_from("<III", w, 12 * k)
                yield g, o, s, w[pos:pos + s], True
                pos += s


def _symbol_info(region: Region) -> bytes:
    """ADS symbol information (AdsSymbolEntry) of a region, as TwinCAT 3 answers 16#F009 (and 16#F00B per
    symbol): the fixed fields, name, type and comment (each NUL-terminated), then, as the flags say
    ``ADSSYMBOLFLAG_TYPEGUID`` (16#8), the 16-byte GUID of the data type (here derived from its
    name)."""
    type_name = region.sym.st_type if region.whole else region.st_type
    name = region.name.encode()
    st_type = type_name.encode()
    ads_type = _ADS_TYPES.get(type_name.upper(), constants.ADST_REAL64 if type_name.upper().endswith("LREAL")
                              else constants.ADST_BIGTYPE)
    body = struct.pack("<IIIIIHHH", IG_PLC_DATA, region.offset, region.size, ads_type,
                       constants.ADSSYMBOLFLAG_TYPEGUID, len(name), len(st_type), 0)
    body += name + b"\0" + st_type + b"\0" + b"\0"
    body += uuid.uuid5(uuid.NAMESPACE_URL, f"pmcal:plc-type:{type_name.upper()}").bytes_le
    return struct.pack("<I", 4 + len(body)) + body


def _state(request: AmsPacket) -> bytes:
    return struct.pack("<H", struct.unpack("<H", request.ams_header.state_flags)[0] | 0x0001)


def _error(request: AmsPacket, cmd: int, code: int) -> AmsResponseData:
    """An ADS response carrying ``code`` in its result field (and an empty payload)."""
    tail = b"" if cmd in (constants.ADSCOMMAND_WRITE, constants.ADSCOMMAND_DELDEVICENOTE,
                          constants.ADSCOMMAND_WRITECTRL) else b"\0\0\0\0"
    return AmsResponseData(_state(request), b"\0\0\0\0", struct.pack("<I", code) + tail)


def _flip(data: bytes, pos: int) -> bytes:
    """``data`` with the lowest bit of byte ``pos`` flipped (if there is such a byte)."""
    if not 0 <= pos < len(data):
        return data
    return data[:pos] + bytes([data[pos] ^ 0x01]) + data[pos + 1:]


def _filetime(t: float) -> int:
    return int((t + _FILETIME_EPOCH) * 10_000_000)


class _FramedConnection(AdsClientConnection):
    """One client connection: whole AMS/TCP frames in, one response (or a fault) out, notifications sent."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self._send_lock = threading.Lock()
        self._notes: dict[int, Notification] = {}
        self._notes_lock = threading.Lock()
        self._notifier: threading.Thread | None = None

    def _recv_exact(self, n: int) -> bytes | None:
        buf = bytearray()
        while len(buf) < n:
            try:
                chunk = self.client.recv(min(n - len(buf), 1 << 20))
            except OSError:
                return None
            if not chunk:
                return None
            buf += chunk
        return bytes(buf)

    def _send(self, frame: bytes) -> bool:
        try:
            with self._send_lock:
                self.client.sendall(frame)
            return True
        except OSError:
            return False

    def run(self) -> None:
        mock = self.server.mock
        handler = self.server.handler
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
            response = handler.serve(request, self)
            if response == _DROP:
                break
            if response == _NO_REPLY:
                continue
            if not self._send(self.construct_response(response, request)):
                break
        self._run = False
        try:
            self.client.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.client.close()

    # ---- notifications ------------------------------------------------------------------------
    def add_notification(self, note: Notification) -> int:
        note.handle = self.server.mock.new_notification_handle()
        note.reply_to = self._reply_to
        with self._notes_lock:
            self._notes[note.handle] = note
        if self._notifier is None:
            self._notifier = threading.Thread(target=self._notify_loop, name="ads-mock-notify", daemon=True)
            self._notifier.start()
        return note.handle

    def delete_notification(self, handle: int) -> bool:
        with self._notes_lock:
            return self._notes.pop(handle, None) is not None

    @property
    def _reply_to(self) -> bytes:
        return self._last_source

    def construct_request(self, request_bytes: bytes) -> AmsPacket:
        packet = super().construct_request(request_bytes)
        self._last_source = packet.ams_header.source_net_id + packet.ams_header.source_port
        self._last_target = packet.ams_header.target_net_id + packet.ams_header.target_port
        return packet

    def _notify_loop(self) -> None:
        """Send DeviceNotification frames: on change (checked each cycle time) or cyclically."""
        mock = self.server.mock
        while self._run and not mock.expired():
            now = time.monotonic()
            with self._notes_lock:
                due = [n for n in self._notes.values() if now >= n.due]
            for note in due:
                note.due = now + note.cycle_s
                with mock.twin.lock:
                    value = mock.read_memory(note.offset, note.size)
                if note.mode == constants.ADSTRANS_SERVERONCHA and value == note.last:
                    continue
                note.last = value
                if not self._send(self._notification_frame(note, value)):
                    return
            time.sleep(mock.cycle_s)

    def _notification_frame(self, note: Notification, value: bytes) -> bytes:
        sample = struct.pack("<II", note.handle, len(value)) + value
        stamp = struct.pack("<QI", _filetime(time.time()), 1) + sample
        data = struct.pack("<II", 4 + len(stamp), 1) + stamp
        header = note.reply_to + self._last_target + struct.pack("<HHIII", constants.ADSCOMMAND_DEVICENOTE,
                                                                 0x0004, len(data), 0, 0)
        return struct.pack("<HI", 0, len(header) + len(data)) + header + data


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
            client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            conn = _FramedConnection(handler=self.handler, client=client, address=address, server=self)
            conn.daemon = True
            conn.start()
            self.clients = [c for c in self.clients if c.is_alive()] + [conn]
        self._run = False


class AdsMockPlc(MockPlc):
    """A mock PLC serving GVL_CompTable over ADS on 127.0.0.1 (ephemeral port by default).

    ``routes``: AMS NetIDs with a route on this PLC (None: every client has one).

    ``with AdsMockPlc() as plc: push(AdsLink(AdsTarget.parse(plc.target)), table)``
    """

    transport = "ads"

    def __init__(self, *args, amap: AdsMap = AdsMap(), symbols: tuple[Symbol, ...] = SYMBOLS,
                 routes=None, read_only: frozenset[str] | None = None, **kwargs) -> None:
        """``symbols``: the GVL as this PLC program declares it (another one models an old program);
        ``read_only``: ST names with read-only symbol access (default: as the shipped GVL declares)."""
        super().__init__(*args, **kwargs)
        self.amap = amap
        # TwinCAT generates no ADS symbol for a variable under {attribute 'hide'} (Infosys tc3_plc_intro,
        # Attribute 'hide'): such a variable of the program is not served (0x710 symbol not found)
        self.symbols = symbols = tuple(s for s in symbols if self.twin.has_symbol(s.key))
        self.area = GvlArea(amap, symbols)
        self.routes = None if routes is None else frozenset(routes)
        self.read_only = read_only_symbols() if read_only is None else frozenset(read_only)
        self.ads_state = constants.ADSSTATE_RUN
        self.handles: dict[int, Region] = {}
        self._next_handle = 0x1000_0001
        self._next_note = 1
        self._overlay: dict[str, tuple[int, bytes]] = {}
        self._server: _FramedServer | None = None

    # ---- identity ----------------------------------------------------------------------------
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

    def plc_state(self) -> int:
        """The ADS state of the PLC runtime: RUN, or STOP (stopped by :meth:`stop_plc` or by the runtime)."""
        return constants.ADSSTATE_STOP if self.task_stopped() else self.ads_state

    # ---- PLC memory through the twin ------------------------------------------------------------
    def location(self, key: str) -> tuple[int, int]:
        region = next(r for r in self.area.regions if r.sym.key == key)
        return region.offset, region.size

    def read_memory(self, offset: int, size: int) -> bytes:
        """``size`` bytes of the data area at ``offset`` (padding reads as zeros). Caller holds twin.lock."""
        out = bytearray(size)
        for region, at, pos, n in self.area.spans(offset, size):
            out[pos:pos + n] = self._variable(region.sym.key)[at:at + n]
        return bytes(out)

    def write_memory(self, offset: int, data: bytes) -> None:
        """Write the data area; partial writes of a variable are read-modify-write. Caller holds twin.lock."""
        for region, at, pos, n in self.area.spans(offset, len(data)):
            key = region.sym.key
            value = data[pos:pos + n]
            if n != region.size:
                whole = bytearray(self._variable(key))
                whole[at:at + n] = value
                value = bytes(whole)
            try:
                self.twin.write_symbol(key, value)
                self._overlay.pop(key, None)
            except PermissionError:          # PLC-owned: holds until the task writes it again
                self._overlay[key] = (self.twin.state.cycle, value)

    def _variable(self, key: str) -> bytes:
        held = self._overlay.get(key)
        if held is not None:
            if key == "interface_version" or held[0] == self.twin.state.cycle:
                return held[1]
            del self._overlay[key]
        return self.twin.read_symbol(key)

    def new_handle(self, region: Region) -> int:
        handle, self._next_handle = self._next_handle, self._next_handle + 1
        self.handles[handle] = region
        return handle

    def new_notification_handle(self) -> int:
        handle, self._next_note = self._next_note, self._next_note + 1
        return handle

    def _reset_volatile(self) -> None:
        """A restart forgets handles and ADS-written values of PLC-owned variables (numbers never reused)."""
        self.handles.clear()
        self._overlay.clear()

    # ---- server ---------------------------------------------------------------------------------
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

