"""ADS client (pyads) for the compensation-table interface: a thin typed :class:`pmcal.bridge.transfer.PlcLink`.

Every access goes through a symbol handle with an explicit ctypes type of the symbol's exact size.
Round trips are few, with ADS sum commands (Beckhoff InfoSys, "ADS-Sum Command"): the interface
check fetches every symbol's information and handle in one 16#F082 request, staging writes header
and table in one 16#F081 request by handle, the read-back reads both in one 16#F080 request, and
``close`` releases every handle in one more. Each sub-request carries its own ADS result code.
Writes are limited to an allow-list (default: the symbols a push needs). pyads does not reconnect
by itself: on a link error the caller closes and reopens (:func:`pmcal.bridge.transfer.push`).

Example::

    link = AdsLink(AdsTarget.parse("5.80.201.232.1.1@192.168.1.10"))
    report = push(link, CompTable.load("comp.json"))
"""

from __future__ import annotations

import ctypes
import struct

import pyads
from pyads import constants
from pyads.errorcodes import ERROR_CODES
from pyads.structs import SAdsSumRequest

from pmcal.bridge.ads_map import LINK_ERRORS, AdsMap, AdsTarget, ctype_of
from pmcal.bridge.errors import DeviceError, InterfaceError, LinkError, WriteNotAllowed
from pmcal.bridge.link import LinkBase
from pmcal.bridge.plc_types import INTERFACE_VERSION, PUSH_WRITES, SHADOW_SIZE, SYMBOL


class AdsLink(LinkBase):
    """One ADS connection to GVL_CompTable. ``writes``: keys of the symbols it may write."""

    transport = "ads"
    #: 16#F082, ADS sum read-write (not among pyads' constants)
    SUMUP_READWRITE = 0xF082
    #: read length asked for one symbol information entry (AdsSymbolEntry with our names fits easily)
    INFO_READ_SIZE = 512

    def __init__(self, target: AdsTarget, *, amap: AdsMap = AdsMap(), writes: frozenset[str] = PUSH_WRITES,
                 timeout_s: float = 2.0) -> None:
        self.address = target
        self.amap = amap
        self.writes = frozenset(writes)
        self.timeout_s = timeout_s
        self.target = str(target)
        self._plc: pyads.Connection | None = None
        self._handles: dict[str, int] = {}

    # ---- connection -----------------------------------------------------------------------
    def open(self) -> None:
        if self._plc is not None:
            return
        plc = pyads.Connection(self.address.netid, self.amap.ams_port,
                               f"{self.address.host}:{self.address.tcp_port}")
        self._call(OPEN_STEP, plc.open)
        self._plc = plc
        self._call("set the ADS time-out", plc.set_timeout, int(self.timeout_s * 1000))

    def close(self) -> None:
        """Release handles (one sum write, best effort) and close; safe to call twice or after a broken link."""
        plc = self._plc
        if plc is None:
            return
        handles = list(self._handles.values())
        self._handles.clear()
        if handles:
            try:
                self._sum_write([(constants.ADSIGRP_SYM_RELEASEHND, 0, struct.pack("<I", h)) for h in handles],
                                "release the symbol handles")
            except (LinkError, DeviceError):
                pass           # the link is gone; handles end with the PLC's restart
        self._plc = None
        try:
            plc.close()
        except (pyads.ADSError, RuntimeError, OSError):
            pass

    # ---- interface --------------------------------------------------------------------------
    def check_interface(self) -> None:
        """PLC in RUN; every GVL_CompTable symbol present with the declared type and size."""
        ads_state, _ = self._call("read the PLC state", self._conn().read_state)
        if ads_state != constants.ADSSTATE_RUN:
            raise InterfaceError(f"PLC at {self.target} is not in RUN (ADS state {ads_state})")
        symbols = self.amap.symbols
        names = [self.amap.name(sym.key) for sym in symbols]
        requests = []
        for name in names:                       # information and handle of every symbol, one round trip
            wire = name.encode() + b"\0"
            requests += [(constants.ADSIGRP_SYM_INFOBYNAMEEX, 0, self.INFO_READ_SIZE, wire),
                         (constants.ADSIGRP_SYM_HNDBYNAME, 0, 4, wire)]
        answers = self._sum_read_write(requests, "look up the GVL_CompTable symbols")
        stale = list(self._handles.values())
        self._handles = {sym.key: struct.unpack("<I", answers[2 * k + 1][1][:4])[0]
                         for k, sym in enumerate(symbols) if not answers[2 * k + 1][0]}   # close() frees them
        if stale:
            self._sum_write([(constants.ADSIGRP_SYM_RELEASEHND, 0, struct.pack("<I", h)) for h in stale],
                            "release the symbol handles")
        for k, (sym, name) in enumerate(zip(symbols, names)):
            code = answers[2 * k][0] or answers[2 * k + 1][0]
            if code:
                raise InterfaceError(f"PLC at {self.target} refused to look up {name}: ADS error "
                                     f"{code} ({_text(code)}): PLC code does not declare {name}")
            size, st_type = _parse_symbol_info(answers[2 * k][1])
            if size != sym.size or _norm(st_type) != _norm(sym.st_type):
                raise InterfaceError(f"{name} on the PLC is {st_type} ({size} bytes), "
                                     f"expected {sym.st_type} ({sym.size} bytes): PLC code does not match")
        version = int.from_bytes(self.read_symbol("interface_version"), "little")
        if version != INTERFACE_VERSION:
            raise InterfaceError(f"GVL_CompTable interface version {version}, bridge speaks {INTERFACE_VERSION}")

    def payload(self, header: bytes, rows: bytes) -> tuple[bytes, bytes]:
        """ADS writes the whole aShadow symbol: ``rows`` padded with zeros to its size."""
        return header, rows + bytes(SHADOW_SIZE - len(rows))

    def stage(self, header: bytes, rows: bytes) -> tuple[bytes, bytes]:
        """Write header and the whole aShadow in one sum write by handle; returns the bytes sent."""
        header, data = self.payload(header, rows)
        for key, value in (("shadow_header", header), ("shadow", data)):
            self._check_write(key, value)
        self._sum_write([(constants.ADSIGRP_SYM_VALBYHND, self._handle("shadow_header"), header),
                         (constants.ADSIGRP_SYM_VALBYHND, self._handle("shadow"), data)],
                        "stage the table (stShadowHeader, aShadow)")
        return header, data

    def read_back(self, data_size: int) -> tuple[bytes, bytes]:
        """Header and aShadow in one sum read by handle; the first ``data_size`` bytes of the table."""
        header, data = self._sum_read([("shadow_header", SYMBOL["shadow_header"].size),
                                       ("shadow", SYMBOL["shadow"].size)], "read back the staged table")
        return header, data[:data_size]

    # ---- symbol access ------------------------------------------------------------------------
    def _conn(self) -> pyads.Connection:
        if self._plc is None:
            raise LinkError(f"ADS link to {self.target} is not open")
        return self._plc

    def _handle(self, key: str) -> int:
        if key not in self._handles:
            name = self.amap.name(key)
            self._handles[key] = self._call(f"get a handle for {name}", self._conn().get_handle, name)
        return self._handles[key]

    def read_symbol(self, key: str) -> bytes:
        t = ctype_of(SYMBOL[key])
        value = self._call(f"read {self.amap.name(key)}", self._conn().read, constants.ADSIGRP_SYM_VALBYHND,
                           self._handle(key), t, return_ctypes=True)
        return bytes(value)

    def write_symbol(self, key: str, data: bytes) -> None:
        t = self._check_write(key, data)
        self._call(f"write {self.amap.name(key)}", self._conn().write, constants.ADSIGRP_SYM_VALBYHND,
                   self._handle(key), t.from_buffer_copy(data), t)

    def _check_write(self, key: str, data: bytes) -> type:
        """The ctypes type of ``key``; WriteNotAllowed outside the allow-list or for a wrong size."""
        name = self.amap.name(key)
        if key not in self.writes:
            raise WriteNotAllowed(f"refusing to write {name}: not in this client's allow-list")
        t = ctype_of(SYMBOL[key])
        if len(data) != ctypes.sizeof(t):
            raise WriteNotAllowed(f"refusing to write {len(data)} bytes to {name} of {ctypes.sizeof(t)} bytes")
        return t

    # ---- sum commands -------------------------------------------------------------------------
    def _sum_write(self, items: list[tuple[int, int, bytes]], what: str) -> None:
        """16#F081: (index group, index offset, data) each; raises on the first failed sub-request."""
        buf = bytearray(b"".join(struct.pack("<III", g, o, len(d)) for g, o, d in items))
        buf += b"".join(d for _, _, d in items)
        codes = self._call(what, self._conn().read_write, constants.ADSIGRP_SUMUP_WRITE, len(items), None, buf,
                           None, return_ctypes=True)
        self._check_codes(struct.unpack(f"<{len(items)}I", bytes(codes)), what)

    def _sum_read(self, items: list[tuple[str, int]], what: str) -> list[bytes]:
        """16#F080 by handle: (symbol key, size) each; the values in order."""
        req = (SAdsSumRequest * len(items))()
        for r, (key, size) in zip(req, items):
            r.iGroup, r.iOffset, r.size = constants.ADSIGRP_SYM_VALBYHND, self._handle(key), size
        raw = bytes(self._call(what, self._conn().read_write, constants.ADSIGRP_SUMUP_READ, len(items), None, req,
                               None, return_ctypes=True))
        n = len(items)
        self._check_codes(struct.unpack_from(f"<{n}I", raw), what)
        out, pos = [], 4 * n
        for _, size in items:
            out.append(raw[pos:pos + size])
            pos += size
        return out

    def _sum_read_write(self, items: list[tuple[int, int, int, bytes]], what: str) -> list[tuple[int, bytes]]:
        """16#F082: (group, offset, read length, write data) each; (ADS result, data) per sub-request."""
        n = len(items)
        write = b"".join(struct.pack("<IIII", g, o, r, len(w)) for g, o, r, w in items) + \
            b"".join(w for *_, w in items)
        read_len = 8 * n + sum(r for _, _, r, _ in items)
        raw = bytes(self._call(what, self._conn().read_write, self.SUMUP_READWRITE, n, ctypes.c_ubyte * read_len,
                               write, ctypes.c_ubyte * len(write), return_ctypes=True, check_length=False))
        heads = [struct.unpack_from("<II", raw, 8 * k) for k in range(n)]
        out, pos = [], 8 * n
        for code, length in heads:
            out.append((code, raw[pos:pos + length]))
            pos += length
        return out

    def _check_codes(self, codes, what: str) -> None:
        bad = next((c for c in codes if c), 0)
        if bad:
            self._raise(what, bad, _text(bad))

    def _call(self, what: str, fn, *args, **kwargs):
        """Run a pyads call, turning its failures into LinkError (retry) or DeviceError (stop)."""
        try:
            return fn(*args, **kwargs)
        except pyads.ADSError as exc:
            code = getattr(exc, "err_code", None)
            text = exc.msg.strip().rstrip(".") if getattr(exc, "msg", "") else str(exc)
            self._raise(what, code, text)
        except (RuntimeError, OSError) as exc:
            raise LinkError(f"ADS link to {self.target} failed to {what}: {exc}") from None

    def _raise(self, what: str, code: int | None, text: str):
        hints = {**ROUTING_HINTS, **OPEN_HINTS} if what == OPEN_STEP else ROUTING_HINTS
        if code in hints:            # retried: AdsLib also says so while a PLC boots
            a = self.address
            raise LinkError(f"ADS link to {self.target} failed to {what}: ADS error {code} ({text}): "
                            + hints[code].format(port=self.amap.ams_port, host=a.host, tcp=a.tcp_port, netid=a.netid)
                            ) from None
        if code is None or code < 0 or code in LINK_ERRORS:
            hint = f": {TIMEOUT_HINT}" if code == ADS_TIMEOUT else ""
            raise LinkError(f"ADS link to {self.target} failed to {what}: {text}{hint}") from None
        raise DeviceError(f"PLC at {self.target} refused to {what}: ADS error {text}") from None


#: AMS routing errors (Beckhoff InfoSys "ADS Return Codes" 0x6, 0x7) and what the user can do about them
ROUTING_HINTS = {
    6: "no ADS server on AMS port {port} of that NetID: is the PLC runtime started, and is --ams-port right "
       "(851 for the first TwinCAT 3 PLC runtime)?",
    7: "the router does not know that AMS NetID: check the NetID in --ads NETID@HOST and the route on the PLC "
       "for this client's NetID (--local-netid, docs/bridge.md 'Routes')",
}


#: the step of :meth:`AdsLink.open` whose failures :data:`OPEN_HINTS` explain
OPEN_STEP = "open the ADS connection"
#: AdsLib's codes when opening fails: 6 there means no TCP connection to the host's ADS router came about (an
#: unreachable or unrouted host, a refused port), not a missing runtime, which shows only on the first request
OPEN_HINTS = {
    6: "no ADS connection to {host} (TCP port {tcp}, AMS NetID {netid}, AMS port {port}): check that {host} is on "
       "and reachable from here (network, firewall for TCP {tcp}), that the PLC has a route for this client's AMS "
       "NetID (--local-netid, docs/bridge.md 'Routes'), the AMS NetID in --ads NETID@HOST, and --ams-port (851 for "
       "the first TwinCAT 3 PLC runtime)",
}


#: AdsLib's "timeout elapsed": no answer within the time-out; a missing route on the PLC looks exactly so
ADS_TIMEOUT = 1861
TIMEOUT_HINT = ("no answer: the PLC is off or unreachable, or it has no route for this client's AMS NetID "
                "(TwinCAT drops frames from unknown NetIDs without an answer; docs/bridge.md 'Routes')")


def _text(code: int) -> str:
    """pyads' text of an ADS error code ("symbol not found", ...)."""
    return f"{ERROR_CODES.get(code, 'unknown error')}"


def _parse_symbol_info(entry: bytes) -> tuple[int, str]:
    """(size, type name) from an AdsSymbolEntry (16#F009 answer)."""
    size = struct.unpack_from("<I", entry, 12)[0]
    name_len, type_len = struct.unpack_from("<HH", entry, 24)
    start = 30 + name_len + 1
    return size, entry[start:start + type_len].decode("utf-8", "replace")


def _norm(type_name: str) -> str:
    """Type names compare without spaces and case (``ARRAY [0..19999] OF LREAL``)."""
    return "".join(type_name.split()).upper()


def set_local_netid(netid: str) -> None:
    """Set this client's AMS NetID (``a.b.c.d.e.f``) for AdsLib (Linux), before any connection.

    Without it AdsLib derives the NetID from the local IP address plus ``.1.1``; the PLC must have a
    route for whichever NetID is used (docs/bridge.md, 'Routes'). ``ValueError`` for a malformed one.
    """
    parts = netid.split(".")
    if len(parts) != 6 or not all(p.isdigit() and 0 <= int(p) <= 255 for p in parts):
        raise ValueError(f"AMS NetID must be six numbers 0..255 separated by dots, got '{netid}'")
    if hasattr(pyads, "set_local_address"):
        try:
            pyads.set_local_address(netid)
        except (pyads.ADSError, OSError, ValueError) as exc:
            raise ValueError(f"cannot set the local AMS NetID {netid}: {exc}") from None


def set_adslib_log_level(level: int = 3) -> bool:
    """Quieten AdsLib's own stderr logging (0 verbose .. 3 errors only, 4 silent); process-wide.

    For the command line only (one clear line per failure). Returns False if the symbol is absent.
    """
    try:
        ctypes.c_int.in_dll(pyads.pyads_ex._adsDLL, "_ZN6Logger8logLevelE").value = int(level)
        return True
    except (AttributeError, ValueError, OSError):
        return False
