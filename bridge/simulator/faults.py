"""Fault injection for the mock PLCs: what goes wrong, at which point of the transfer, how often.

A mock classifies every request into a :class:`Point` of the hand-over and asks its
:class:`FaultPlan` whether a fault fires there. Both mocks understand every :class:`Kind`:

=========  ==========================================================================================
delay      answer after ``delay_s`` (longer than the client time-out: the client sees a time-out)
no_reply   swallow the request: not applied, never answered
drop       close the connection on that request (not applied)
corrupt    writes are stored with one bit flipped, reads are answered with one bit flipped; at
           ``commit`` the staged table is damaged in PLC memory (the PLC's CRC must catch it)
error      answer with an error: ADS error ``code`` (default 1796, access denied) or Modbus
           exception ``code`` (default 4, server device failure); not applied
busy       answer "device busy": ADS error 0x708 (1800) or Modbus exception 6 (server device busy);
           not applied
=========  ==========================================================================================
"""

from __future__ import annotations

import re
import threading
from dataclasses import dataclass, field
from enum import Enum


class Point(str, Enum):
    """Where in the transfer a request belongs (as the mock sees it)."""

    BEFORE_STAGE = "before_stage"    # interface check, state reads and withdrawal before staging
    MID_STAGE = "mid_stage"          # staging writes after the first one (ADS: aShadow; Modbus: window)
    AFTER_STAGE = "after_stage"      # read-back of the staged table, after staging and before the commit
    COMMIT = "commit"                # the commit write itself
    ACK_WAIT = "ack_wait"            # state reads while a commit is pending or acknowledged


class Kind(str, Enum):
    DELAY = "delay"
    NO_REPLY = "no_reply"
    DROP = "drop"
    CORRUPT = "corrupt"
    ERROR = "error"
    BUSY = "busy"


@dataclass
class Fault:
    """One fault: ``kind`` at ``at``, firing ``times`` times (None: every time until cleared).

    ``delay_s``: for ``delay`` how long the answer is held (default 1 s); for ``drop`` and
    ``no_reply`` how long the mock waits before the fault acts (default 0: at once).
    """

    kind: Kind
    at: Point
    times: int | None = None
    delay_s: float | None = None
    code: int | None = None

    @property
    def wait_s(self) -> float:
        """Seconds to wait before acting (see ``delay_s``); corrupt and error act at once."""
        if self.kind not in (Kind.DELAY, Kind.DROP, Kind.NO_REPLY):
            return 0.0
        if self.delay_s is None:
            return 1.0 if self.kind == Kind.DELAY else 0.0
        return float(self.delay_s)

    @classmethod
    def parse(cls, text: str) -> "Fault":
        """``KIND@POINT[*N]``, e.g. ``drop@mid_stage`` or ``no_reply@ack_wait*1`` (for the CLI)."""
        m = re.fullmatch(r"([a-z_]+)@([a-z_]+)(?:\*(\d+))?", text.strip())
        try:
            if m is None:
                raise ValueError(text)
            return cls(Kind(m[1]), Point(m[2]), int(m[3]) if m[3] else None)
        except ValueError:
            raise ValueError(f"fault {text!r}: expected KIND@POINT[*N] with KIND in "
                             f"{[k.value for k in Kind]} and POINT in {[p.value for p in Point]}") from None


@dataclass
class FaultPlan:
    """The faults armed on one mock; thread-safe. ``fired`` counts the faults that fired."""

    faults: list[Fault] = field(default_factory=list)
    fired: int = 0
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def arm(self, *faults: Fault) -> None:
        with self._lock:
            self.faults.extend(faults)

    def clear(self) -> None:
        with self._lock:
            self.faults.clear()

    def trigger(self, point: Point) -> Fault | None:
        """The fault that fires for a request at ``point`` (consumes one of its ``times``)."""
        with self._lock:
            for f in self.faults:
                if f.at == point and (f.times is None or f.times > 0):
                    if f.times is not None:
                        f.times -= 1
                    self.fired += 1
                    return f
        return None
