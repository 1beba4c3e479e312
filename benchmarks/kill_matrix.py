"""Kill matrix: a real ``pmcal push`` is killed (SIGKILL), has its link cut, or loses its PLC to a power
cut at random moments of the hand-over, over ADS and Modbus; after each, the next push must succeed
within the staging lease + 5 s, and no mixed or half table may ever be active.

The mock PLC runs in this process (so its active buffer can be compared bit for bit); the push that
is disturbed is a subprocess ``python -m pmcal.cli push``; the next push runs :func:`push` in this
process, retried every 0.25 s until it succeeds (so Python start-up, seconds on a loaded machine, does
not blur the lock-out time), and ``recovered_s`` is the time from the event to its success. The moment of an event is a request of the push as the mock
sees it: the phases (interface check and claim, staging, read-back, commit, acknowledgement) in turn,
a random request within the phase; every tenth kill lands at a random time during the client's
start-up instead. Events:

- ``kill``: SIGKILL of the push process while the mock holds that request 50 ms;
- ``cut``: from that request on, the mock drops every connection of the push (the cable is pulled)
  until the push gives up; the next push measures from then;
- ``power``: the mock PLC loses power at that request (:meth:`MockPlc.power_cut`) and comes back
  after ``restart_s``; the next push measures from its return.

A monitor thread samples the active table every 2 ms and compares it with the candidate tables
(the one active before, the one pushed, the one pushed next) byte for byte: ``mixed`` counts the
samples that match none.

Run: python benchmarks/kill_matrix.py [--transport ads|modbus|both] [--kills 25] [--cuts 5]
     [--power-cuts 3] [--lease 3] [--seed 1] [--grid 37,13] [--json PATH]
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchmarks.common import print_table, write_json  # noqa: E402
from pmcal.bridge.ads import AdsLink, set_adslib_log_level  # noqa: E402
from pmcal.bridge.simulator.ads_mock import AdsMockPlc  # noqa: E402
from pmcal.bridge.comptable import CompTable  # noqa: E402
from pmcal.bridge.errors import BridgeError  # noqa: E402
from pmcal.bridge.simulator.faults import Fault, Kind, Point  # noqa: E402
from pmcal.bridge.modbus import ModbusLink  # noqa: E402
from pmcal.bridge.simulator.modbus_mock import ModbusMockPlc  # noqa: E402
from pmcal.bridge.transfer import push  # noqa: E402
from pmcal.errors import InputError  # noqa: E402
from pmcal.mechanism.ocpm.kinematics import nominal_ik  # noqa: E402

#: the margin the issue allows above the staging lease for the next push to succeed, s
MARGIN_S = 5.0
PUSH_TIMEOUT_S = 60.0
#: pause between attempts of the next push, s (a tool retrying)
RETRY_S = 0.25


def make_table(version: int, grid: tuple[int, int]) -> CompTable:
    """A valid table from the nominal IK (deg), offset by the version so tables differ."""
    return CompTable.from_setpoints(
        lambda p, t: np.rad2deg(nominal_ik(np.deg2rad(p), np.deg2rad(t))) + 1e-3 * version,
        machine="ocpm_2dof", version=version, n_phi=grid[0], n_theta=grid[1], motor_limits_deg=(-150.0, 60.0))


@dataclass
class Trial:
    """One event and what followed it."""

    transport: str
    event: str                   # kill | cut | power
    at_request: int              # the push's k-th request as the mock saw it (0: during start-up)
    point: str                   # phase of that request (faults.Point), or "startup"
    active_after_event: int      # table version active right after the event
    recovered_s: float           # event -> next push succeeded (inf: never within the deadline)
    next_attempts: int           # pushes run until one succeeded
    ok: bool                     # next push within lease + margin, and the right table active
    mixed: int                   # monitor samples matching no candidate table
    note: str = ""

    @property
    def happened(self) -> bool:
        """The event fired (a push that ended before its k-th request had none)."""
        return self.point != "none"


class Trigger:
    """Stands in for a mock's FaultPlan: counts the push's requests and fires the event at the k-th."""

    def __init__(self, k: int, action, at: Point | None = None) -> None:
        """Fire ``action`` at the k-th request (of those at point ``at``, if given)."""
        self.k, self.action, self.at = k, action, at
        self.count = 0
        self.per_point: dict[Point, int] = {}
        self.point: Point | None = None
        self.fired_at: float | None = None
        self.cut = False
        self.fired = 0
        self._lock = threading.Lock()

    def trigger(self, point: Point) -> Fault | None:
        with self._lock:
            self.per_point[point] = self.per_point.get(point, 0) + 1
            self.count += 1
            if self.cut:
                return Fault(Kind.DROP, point)
            seen = self.count if self.at is None else self.per_point[point] if point == self.at else 0
            if seen != self.k or self.fired_at is not None:
                return None
            self.point, self.fired_at = point, time.monotonic()
        return self.action(point)

    def arm(self, *faults) -> None:            # FaultPlan's interface, unused here
        pass

    def clear(self) -> None:
        pass


class Monitor(threading.Thread):
    """Samples the active table every 2 ms; counts samples that are none of the candidate tables."""

    def __init__(self, twin, candidates: list[CompTable]) -> None:
        super().__init__(daemon=True)
        self.twin = twin
        self.known = {(t.version, t.values.tobytes()) for t in candidates}
        self.mixed = 0
        self.samples = 0
        self._halt = threading.Event()

    def add(self, table: CompTable) -> None:
        self.known.add((table.version, table.values.tobytes()))

    def run(self) -> None:
        while not self._halt.is_set():
            header, values = self.twin.active_table()
            self.samples += 1
            if (header.table_version, values.tobytes()) not in self.known:
                self.mixed += 1
            self._halt.wait(0.002)

    def stop(self) -> None:
        self._halt.set()
        self.join(timeout=2.0)


class Matrix:
    """One mock PLC and the push subprocesses against it."""

    def __init__(self, transport: str, lease_s: float, grid: tuple[int, int], workdir: Path,
                 restart_s: float = 1.0, timeout_s: float = 0.5) -> None:
        self.transport, self.lease_s, self.grid, self.workdir = transport, lease_s, grid, workdir
        self.timeout_s = timeout_s
        mock = AdsMockPlc if transport == "ads" else ModbusMockPlc
        self.mock = mock(lifetime_s=3600.0, restart_s=restart_s, boot_s=min(0.3, restart_s))
        self.mock.start()
        self.mock.set_staging_lease(lease_s)
        self.version = 1
        self.per_point: dict[Point, int] = {}
        self.active = make_table(1, grid)
        self.mock.twin.seed(self.active)

    def close(self) -> None:
        self.mock.stop()

    # ---- subprocesses --------------------------------------------------------------------------
    def _file(self, table: CompTable) -> Path:
        path = self.workdir / f"{self.transport}_v{table.version}.json"
        table.to_json(path)
        return path

    def spawn(self, table: CompTable) -> subprocess.Popen:
        flag = "--ads" if self.transport == "ads" else "--modbus"
        cmd = [sys.executable, "-m", "pmcal.cli", "-q", "push", str(self._file(table)), flag, self.mock.target,
               "--no-audit", "--timeout", str(self.timeout_s)]
        env = dict(os.environ, MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"))
        return subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)

    def link(self):
        """A link of the project to the mock (the next push runs in this process: no start-up time)."""
        if self.transport == "ads":
            return AdsLink(self.mock.address, timeout_s=self.timeout_s)
        return ModbusLink(self.mock.host, self.mock.port, rmap=self.mock.rmap, timeout_s=self.timeout_s)

    def requests_per_push(self, pushes: int = 1) -> int:
        """Requests (as fault points see them) of an undisturbed push (the fewest of ``pushes``);
        :attr:`per_point` keeps the fewest per phase. Pushes them."""
        counts = []
        for _ in range(pushes):
            counter = Trigger(10 ** 9, lambda p: None)
            self.mock.faults = counter
            table = self._next_table()
            proc = self.spawn(table)
            out, err = proc.communicate(timeout=PUSH_TIMEOUT_S)
            if proc.returncode != 0:
                raise SystemExit(f"calibration push failed: {err.strip()}")
            self.active = table
            counts.append(counter.count)
            self.per_point = {p: min(n, self.per_point.get(p, n)) for p, n in counter.per_point.items()}
        return min(counts)

    def _next_table(self) -> CompTable:
        self.version += 1
        return make_table(self.version, self.grid)

    # ---- one event ------------------------------------------------------------------------------
    def trial(self, event: str, k: int, startup_kill_s: float | None = None, at: Point | None = None) -> Trial:
        """One ``event`` at the push's k-th request (of those at phase ``at``, if given), or for a kill
        ``startup_kill_s`` after the push process starts."""
        before, pushed = self.active, self._next_table()
        monitor = Monitor(self.mock.twin, [before, pushed])
        monitor.start()
        power_thread: list[threading.Thread] = []
        procs: list[subprocess.Popen] = []

        def action(point: Point) -> Fault | None:
            if event == "kill":
                os.kill(procs[0].pid, signal.SIGKILL)
                return Fault(Kind.DELAY, point, delay_s=0.05)
            if event == "cut":
                trig.cut = True
                return Fault(Kind.DROP, point)
            th = threading.Thread(target=self.mock.power_cut, daemon=True)
            power_thread.append(th)
            th.start()
            return Fault(Kind.DROP, point)

        trig = Trigger(k, action, at)
        self.mock.faults = trig
        proc = self.spawn(pushed)
        procs.append(proc)
        if startup_kill_s is not None:
            time.sleep(startup_kill_s)
            if trig.count == 0:
                trig.fired_at, trig.k = time.monotonic(), -1
                os.kill(proc.pid, signal.SIGKILL)
        try:
            proc.communicate(timeout=PUSH_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()
        for th in power_thread:
            th.join(timeout=60.0)
        trig.cut = False
        self.mock.faults = Trigger(-1, lambda p: None)
        point = "startup" if trig.k == -1 else (trig.point.value if trig.point else "none")
        start = time.monotonic() if event in ("cut", "power") else (trig.fired_at or time.monotonic())
        if trig.fired_at is None:
            note = "push ended before the event"
        else:
            note = ""
        after_event, _ = self.mock.twin.active_table()
        # the next push, repeated until it succeeds or the deadline passes
        following = self._next_table()
        monitor.add(following)
        deadline = start + self.lease_s + MARGIN_S
        attempts, ok_at, last_err = 0, None, ""
        while time.monotonic() < deadline:
            attempts += 1
            try:
                push(self.link(), following)
                ok_at = time.monotonic()
                break
            except (BridgeError, InputError) as exc:
                last_err = " ".join(str(exc).split())[-160:]
            time.sleep(RETRY_S)
        monitor.stop()
        header, values = self.mock.twin.active_table()
        right = header.table_version == following.version and values.tobytes() == following.values.tobytes()
        if ok_at is not None and right:
            self.active = following
        else:
            self.active = next((t for t in (before, pushed, following)
                                if t.version == header.table_version), before)
            note = (note + "; " if note else "") + (last_err or "wrong table active")
        recovered = (ok_at - start) if ok_at is not None else float("inf")
        if ok_at is None or not right:
            # a locked-out PLC would fail every later trial: restart it (staging cleared) so that
            # each trial measures its own event
            self.mock.restart(down_s=0.2)
            self.mock.faults = Trigger(-1, lambda p: None)
            note += "; PLC restarted before the next trial"
        return Trial(self.transport, event, max(trig.k, 0), point, after_event.table_version,
                     round(recovered, 3), attempts, bool(ok_at is not None and right
                                                         and recovered <= self.lease_s + MARGIN_S),
                     monitor.mixed, note)


def run(transport: str, kills: int, cuts: int, power_cuts: int, lease_s: float, seed: int,
        grid: tuple[int, int], progress=print) -> list[Trial]:
    """The matrix for one transport: ``kills`` SIGKILLs, ``cuts`` cut links, ``power_cuts`` power cuts."""
    rng = np.random.default_rng(seed)
    with tempfile.TemporaryDirectory(prefix="pmcal-kill-") as tmp:
        m = Matrix(transport, lease_s, grid, Path(tmp))
        try:
            n = m.requests_per_push(pushes=3)
            phases = [p for p in Point if m.per_point.get(p, 0) > 0]
            events = ["kill"] * kills + ["cut"] * cuts + ["power"] * power_cuts
            trials = []
            for i, event in enumerate(events):
                startup = event == "kill" and i % 10 == 9            # every tenth kill during start-up
                at = phases[i % len(phases)]                         # every phase in turn
                k = 10 ** 9 if startup else int(rng.integers(1, m.per_point[at] + 1))
                t = m.trial(event, k, startup_kill_s=float(rng.uniform(0.05, 0.5)) if startup else None, at=at)
                trials.append(t)
                progress(f"{transport} {i + 1}/{len(events)}: {event} at {t.point} request {t.at_request} "
                         f"-> next push {'ok' if t.ok else 'FAILED'} after {t.recovered_s} s, "
                         f"{t.next_attempts} attempt(s), mixed {t.mixed} {t.note}")
            return trials
        finally:
            m.close()


def summarize(trials: list[Trial], lease_s: float) -> list[dict]:
    rows = []
    for transport in sorted({t.transport for t in trials}):
        for event in ("kill", "cut", "power"):
            ts = [t for t in trials if t.transport == transport and t.event == event and t.happened]
            if not ts:
                continue
            rec = np.array([t.recovered_s for t in ts])
            finite = rec[np.isfinite(rec)]
            rows.append({"transport": transport, "event": event, "n": len(ts), "ok": sum(t.ok for t in ts),
                         "failed": sum(not t.ok for t in ts), "mixed": sum(t.mixed for t in ts),
                         "recovered_median_s": float(np.median(finite)) if finite.size else None,
                         "recovered_max_s": float(finite.max()) if finite.size else None,
                         "deadline_s": lease_s + MARGIN_S,
                         "not_fired": sum(1 for t in trials if t.transport == transport and t.event == event
                                          and not t.happened),
                         "points": sorted({t.point for t in ts})})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--transport", choices=("ads", "modbus", "both"), default="both")
    ap.add_argument("--kills", type=int, default=25, help="SIGKILLs per transport (default 25)")
    ap.add_argument("--cuts", type=int, default=5, help="cut links per transport (default 5)")
    ap.add_argument("--power-cuts", type=int, default=3, help="power cuts per transport (default 3)")
    ap.add_argument("--lease", type=float, default=3.0, help="staging lease of the mock PLC, s (default 3)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--grid", default="37,13", help="table grid NPHI,NTHETA (default 37,13)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    set_adslib_log_level(4)
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    grid = tuple(int(x) for x in args.grid.split(","))
    transports = ("ads", "modbus") if args.transport == "both" else (args.transport,)
    trials = []
    for i, transport in enumerate(transports):
        trials += run(transport, args.kills, args.cuts, args.power_cuts, args.lease, args.seed + i, grid)
    rows = summarize(trials, args.lease)
    print_table(f"kill matrix: next push within lease {args.lease:g} s + {MARGIN_S:g} s; mixed = samples of the "
                "active table matching no candidate",
                ["transport", "event", "n", "ok", "failed", "mixed", "recovered median s", "recovered max s",
                 "deadline s", "phases hit"],
                [[r["transport"], r["event"], r["n"], r["ok"], r["failed"], r["mixed"],
                  "-" if r["recovered_median_s"] is None else r["recovered_median_s"],
                  "-" if r["recovered_max_s"] is None else r["recovered_max_s"], r["deadline_s"],
                  ",".join(r["points"])] for r in rows])
    name = "kill_matrix" if args.transport == "both" else f"kill_matrix_{args.transport}"
    write_json(name, {"lease_s": args.lease, "margin_s": MARGIN_S, "grid": list(grid), "seed": args.seed,
                      "summary": rows, "trials": [asdict(t) for t in trials]}, args.json)


if __name__ == "__main__":
    main()
