"""What both mock PLCs share: a :class:`PlcTwin` running as a cyclic task, a fault plan, a lifetime.

A mock serves on 127.0.0.1 only, on an ephemeral port unless told otherwise, and stops by itself
after ``lifetime_s`` (its server loop and the PLC task both check the deadline).

Restarts are as slow as on a CX: after :meth:`MockPlc.restart` or :meth:`MockPlc.power_cut` nothing
listens for ``restart_s`` (default 5 s: the CX boots), then for ``boot_s`` of that time the router
answers but the PLC runtime is not there yet (ADS error 6; Modbus: connection refused until TF6250
runs), then the task runs again.
"""

from __future__ import annotations

import threading
import time

from pmcal.bridge.simulator.faults import FaultPlan
from pmcal.bridge.simulator.plc_runtime import PlcTwin

LOOPBACK = "127.0.0.1"
#: seconds a CX without the PLC takes from power-on (or a restart) to a running PLC task
RESTART_S = 5.0
#: of which the last part: the router answers, the PLC runtime is not loaded yet
BOOT_S = 1.0


class MockPlc:
    """Base of :class:`pmcal.bridge.simulator.ads_mock.AdsMockPlc` and :class:`pmcal.bridge.simulator.modbus_mock.ModbusMockPlc`."""

    transport = ""

    def __init__(self, twin: PlcTwin | None = None, faults: FaultPlan | None = None, *,
                 port: int = 0, cycle_s: float = 0.001, lifetime_s: float = 600.0,
                 restart_s: float = RESTART_S, boot_s: float = BOOT_S) -> None:
        self.twin = twin if twin is not None else PlcTwin()
        self.faults = faults if faults is not None else FaultPlan()
        self.host = LOOPBACK
        self.port = port
        self.cycle_s = cycle_s
        self.lifetime_s = lifetime_s
        self.deadline = time.monotonic() + lifetime_s
        self.restart_s = restart_s
        self.boot_s = min(boot_s, restart_s)
        self._booting_until = 0.0
        self._task_halted = False
        self.power_cuts = 0
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

    def restart(self, down_s: float | None = None) -> None:
        """A clean restart (UPS, or a reset from the engineering system): the task and the server stop
        (clients lose their connections), the volatile memory clears, persistent data stay
        (:meth:`PlcTwin.restart`), and after ``down_s`` (default ``restart_s``) the PLC runs again on
        the same port."""
        self._down(down_s, power_cut=False)

    def power_cut(self, down_s: float | None = None) -> None:
        """Power lost on a CX without UPS: connections drop at once, RAM is lost, and PERSISTENT data
        come back as last saved (by WritePersistentData), not as they were; then a restart as
        :meth:`restart`."""
        self._down(down_s, power_cut=True)

    def reset_cold(self, down_s: float | None = None) -> None:
        """Online command Reset cold from the engineering system (then a start): PERSISTENT data stay,
        every other variable, RETAIN included, starts from its initial value (:meth:`PlcTwin.reset_cold`)."""
        self._down(down_s, power_cut=False, event="reset_cold")

    def download(self, down_s: float | None = None) -> None:
        """A download of the same PLC program (then a start): PERSISTENT data stay (:meth:`PlcTwin.download`)."""
        self._down(down_s, power_cut=False, event="download")

    def _down(self, down_s: float | None, power_cut: bool, event: str = "") -> None:
        down_s = self.restart_s if down_s is None else down_s
        self.twin.stop()
        self._stop_server()
        if power_cut:
            self.twin.power_cut()
        elif event:
            getattr(self.twin, event)()
        else:
            self.twin.restart()
        self.power_cuts += int(power_cut)
        self._reset_volatile()
        boot = min(self.boot_s, down_s)
        time.sleep(down_s - boot)
        self._booting_until = time.monotonic() + boot
        self._start_server()
        time.sleep(boot)
        self._task_halted = False
        before, after = self._task_hooks()
        self.twin.start(self.cycle_s, max(0.0, self.deadline - time.monotonic()), before=before, after=after)

    def booting(self) -> bool:
        """The router is up but the PLC runtime is not (the last ``boot_s`` of a restart)."""
        return time.monotonic() < self._booting_until

    def stop_plc(self) -> None:
        """The PLC goes to STOP (as from the engineering system or after an exception): the task no
        longer runs; the server keeps answering."""
        self._task_halted = True
        self.twin.stop()

    def start_plc(self) -> None:
        """Back to RUN after :meth:`stop_plc`."""
        if self._task_halted:
            self._task_halted = False
            before, after = self._task_hooks()
            self.twin.start(self.cycle_s, max(0.0, self.deadline - time.monotonic()), before=before, after=after)

    def task_stopped(self) -> bool:
        """The PLC task does not run: stopped by :meth:`stop_plc`, or halted by the runtime itself
        (an FPU exception or a division by zero in the ST, where the runtime reports it)."""
        return self._task_halted or self.twin.stopped or self.twin.fault is not None

    def set_staging_lease(self, seconds: float) -> None:
        """Shorten the PLC's staging lease (the kill-matrix study; a GVL constant on a real PLC)."""
        self.twin.staging_lease_s = float(seconds)

    def _reset_volatile(self) -> None:
        """Transport-side PLC memory that a restart clears (e.g. the Modbus area in %M)."""

    def expired(self) -> bool:
        return time.monotonic() >= self.deadline

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
