"""ADS client (pyads) for the compensation-table interface: a thin typed :class:`pmcal.bridge.transfer.PlcLink`.

Every access goes through a symbol handle with an explicit ctypes type of the symbol's exact size.
Writes are limited to an allow-list (default: the three symbols a push needs). pyads does not
reconnect by itself: on a link error the caller closes and reopens (:func:`pmcal.bridge.transfer.push`).

Example::

    link = AdsLink(AdsTarget.parse("5.80.201.232.1.1@192.168.1.10"))
    report = push(link, CompTable.load("comp.json"))
"""

from __future__ import annotations

import ctypes

import pyads
from pyads import constants

from pmcal.bridge.ads_map import LINK_ERRORS, AdsMap, AdsTarget, ctype_of
from pmcal.bridge.errors import DeviceError, InterfaceError, LinkError, WriteNotAllowed
from pmcal.bridge.link import LinkBase
from pmcal.bridge.plc_types import INTERFACE_VERSION, PUSH_WRITES, SHADOW_SIZE, SYMBOL


class AdsLink(LinkBase):
    """One ADS connection to GVL_CompTable. ``writes``: keys of the symbols it may write."""

    transport = "ads"

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
        self._call("open the ADS connection", plc.open)
        self._plc = plc
        self._call("set the ADS time-out", plc.set_timeout, int(self.timeout_s * 1000))

    def close(self) -> None:
        """Release handles (best effort) and close; safe to call twice or after a broken link."""
        plc, self._plc = self._plc, None
        if plc is None:
            return
        for handle in self._handles.values():
            try:
                plc.release_handle(handle)
            except (pyads.ADSError, RuntimeError, OSError):
                break          # the link is gone; the PLC frees handles of dead connections
        self._handles.clear()
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
        for sym in self.amap.symbols:
            name = self.amap.name(sym.key)
            try:
                info = self._call(f"look up {name}", self._conn().read_write, constants.ADSIGRP_SYM_INFOBYNAMEEX,
                                  0, pyads.structs.SAdsSymbolEntry, name, pyads.PLCTYPE_STRING,
                                  return_ctypes=True, check_length=False)
            except DeviceError as exc:
                raise InterfaceError(f"{exc}: PLC code does not declare {name}") from None
            if info.size != sym.size or _norm(info.symbol_type) != _norm(sym.st_type):
                raise InterfaceError(f"{name} on the PLC is {info.symbol_type} ({info.size} bytes), "
                                     f"expected {sym.st_type} ({sym.size} bytes): PLC code does not match")
        version = int.from_bytes(self.read_symbol("interface_version"), "little")
        if version != INTERFACE_VERSION:
            raise InterfaceError(f"GVL_CompTable interface version {version}, bridge speaks {INTERFACE_VERSION}")

    def payload(self, header: bytes, rows: bytes) -> tuple[bytes, bytes]:
        """ADS writes the whole aShadow symbol: ``rows`` padded with zeros to its size."""
        return header, rows + bytes(SHADOW_SIZE - len(rows))

    def stage(self, header: bytes, rows: bytes) -> tuple[bytes, bytes]:
        """Write header and the whole aShadow; returns the bytes sent."""
        header, data = self.payload(header, rows)
        self.write_symbol("shadow_header", header)
        self.write_symbol("shadow", data)
        return header, data

    def read_back(self, data_size: int) -> tuple[bytes, bytes]:
        return self.read_symbol("shadow_header"), self.read_symbol("shadow")[:data_size]

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
        name = self.amap.name(key)
        if key not in self.writes:
            raise WriteNotAllowed(f"refusing to write {name}: not in this client's allow-list")
        t = ctype_of(SYMBOL[key])
        if len(data) != ctypes.sizeof(t):
            raise WriteNotAllowed(f"refusing to write {len(data)} bytes to {name} of {ctypes.sizeof(t)} bytes")
        self._call(f"write {name}", self._conn().write, constants.ADSIGRP_SYM_VALBYHND, self._handle(key),
                   t.from_buffer_copy(data), t)

    def _call(self, what: str, fn, *args, **kwargs):
        """Run a pyads call, turning its failures into LinkError (retry) or DeviceError (stop)."""
        try:
            return fn(*args, **kwargs)
        except pyads.ADSError as exc:
            code = getattr(exc, "err_code", None)
            text = exc.msg.strip().rstrip(".") if getattr(exc, "msg", "") else str(exc)
            if code in ROUTING_HINTS:            # retried: AdsLib also says so while a PLC boots
                raise LinkError(f"ADS link to {self.target} failed to {what}: ADS error {code} ({text}): "
                                  f"{ROUTING_HINTS[code].format(port=self.amap.ams_port)}") from None
            if code is None or code < 0 or code in LINK_ERRORS:
                raise LinkError(f"ADS link to {self.target} failed to {what}: {text}") from None
            raise DeviceError(f"PLC at {self.target} refused to {what}: ADS error {text}") from None
        except (RuntimeError, OSError) as exc:
            raise LinkError(f"ADS link to {self.target} failed to {what}: {exc}") from None


#: AMS routing errors (Beckhoff InfoSys "ADS Return Codes" 0x6, 0x7) and what the user can do about them
ROUTING_HINTS = {
    6: "no ADS server on AMS port {port} of that NetID: is the PLC runtime started, and is --ams-port right "
       "(851 for the first TwinCAT 3 PLC runtime)?",
    7: "the router does not know that AMS NetID: check the NetID in --ads NETID@HOST and the route on the PLC "
       "for this client's NetID (--local-netid, docs/bridge.md 'Routes')",
}


def _norm(type_name: str) -> str:
    """Type names compare without spaces and case (``ARRAY [0..99,0..99,0..1] OF LREAL``)."""
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
