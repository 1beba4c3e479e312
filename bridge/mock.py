"""What both mock PLCs share: a :class:`PlcTwin` running as a cyclic task, a fault plan, a lifetime.

A mock serves on 127.0.0.1 only, on an ephemeral port unless told otherwise, and stops by itself
after ``lifetime_s`` (its server loop and the PLC task both check the deadline).
"""

from __future__ import annotations

import threading
import time

from pmcal.bridge.faults import FaultPlan
from pmcal.bridge.plc_runtime import PlcTwin

LOOPBACK = "127.0.0.1"


class MockPlc:
    """Base of :class:`pmcal.bridge.ads_mock.AdsMockPlc` and :class:`pmcal.bridge.modbus_mock.ModbusMockPlc`."""

    transport = ""

    def __init__(self, twin: PlcTwin | None = None, faults: FaultPlan | None = None, *,
                 port: int = 0, cycle_s: float = 0.001, lifetime_s: float = 600.0) -> None:
        self.twin = twin if twin is not None else PlcTwin()
        self.faults = faults if faults is not None else FaultPlan()
        self.host = LOOPBACK
        self.port = port
        self.cycle_s = cycle_s
        self.lifetime_s = lifetime_s
        self.deadline = time.monotonic() + lifetime_s
        self.requests = 0           # requests served, and how many of them wrote PLC memory
        self.writes = 0
        self._count_lock = threading.Lock()

    def count(self, write: bool) -> None:
        with self._count_lock:
            self.requests += 1
            self.writes += int(write)

    @property
    def target(self) -> str:
        """The target string ``pmcal push`` takes for this mock."""
        raise NotImplementedError

    def _start_server(self) -> None:
        raise NotImplementedError

    def _stop_server(self) -> None:
        raise NotImplementedError

    def _task_hooks(self) -> tuple[tuple, tuple]:
        """Callables the PLC task runs before and after each cycle (e.g. the Modbus area mapping)."""
        return (), ()

    def start(self) -> "MockPlc":
        self.deadline = time.monotonic() + self.lifetime_s
        self._start_server()
        before, after = self._task_hooks()
        self.twin.start(self.cycle_s, self.lifetime_s, before=before, after=after)
        return self

    def stop(self) -> None:
        self.twin.stop()
        self._stop_server()

    def restart(self, down_s: float = 0.0) -> None:
        """Power-cycle the PLC: the task and the server stop (clients lose their connections), the
        volatile memory clears, persistent data stay (:meth:`PlcTwin.restart`), and after ``down_s``
        the server comes back on the same port."""
        self.twin.stop()
        self._stop_server()
        self.twin.restart()
        self._reset_volatile()
        time.sleep(down_s)
        self._start_server()
        before, after = self._task_hooks()
        self.twin.start(self.cycle_s, max(0.0, self.deadline - time.monotonic()), before=before, after=after)

    def _reset_volatile(self) -> None:
        """Transport-side PLC memory that a restart clears (e.g. the Modbus area in %M)."""

    def expired(self) -> bool:
        return time.monotonic() >= self.deadline

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
