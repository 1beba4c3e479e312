"""The PLC runtime: memory, task cycle, simulated clock, persistence, work counters, faults.

One :class:`PlcRuntime` is one TwinCAT PLC runtime with one cyclic task that calls the task's
programs in order every cycle. Time inside the PLC is simulated: ``TIME()`` (and so TON) reads
``cycles x cycle time``, never the wall clock, so a test or a mock thread that runs cycles late
only stretches time, it never skips a step.
"""

from __future__ import annotations

import hashlib
import math
import os
import pickle
import re
import struct
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from pmcal.bridge.simulator.plc_runtime.builtins import PlcException, crc16_ccitt, make_helpers
from pmcal.bridge.simulator.plc_runtime.compiler import LIBRARY_FILE, Compiler, Program
from pmcal.bridge.simulator.plc_runtime.cost_model import CX_SLOWEST, CpuModel
from pmcal.bridge.simulator.plc_runtime.datatypes import DType, strides
from pmcal.bridge.simulator.plc_runtime.source import parse_files, project_files

LIBRARY = Path(__file__).with_name(LIBRARY_FILE)
#: the project's save program and its task's cycle in task cycles (plc/PersistTask.TcTTO: 10 ms at 1 ms)
SAVE_PROGRAM, SAVE_EVERY = "PRG_CompTableSave", 10
#: TwinCAT's implicit GVL TwinCAT_SystemInfoVarList (_AppInfo), compiled with every program
SYSTEM_INFO = Path(__file__).with_name("TwinCAT_SystemInfoVarList.TcGVL")
#: counters per cycle, in this order (``work_last``, ``work_max``)
WORK = ("statements", "math_calls", "bytes_copied", "crc_bytes", "cpu_cycles")
_TRAPS = (PlcException, ZeroDivisionError, ValueError, OverflowError, struct.error)
_CACHE: dict[str, Program] = {}
_CACHE_LOCK = threading.Lock()


@dataclass(frozen=True)
class PlcFault:
    """Why the task stopped: the exception kind, its message, the cycle, and the ST place if known."""

    kind: str
    message: str
    cycle: int
    where: str = ""

    def __str__(self) -> str:
        at = f" in {self.where}" if self.where else ""
        return f"PLC task stopped in cycle {self.cycle}{at}: {self.message} ({self.kind})"


def _digest(files) -> str:
    h = hashlib.sha256()
    for f in files:
        h.update(str(f.name).encode())
        h.update(f.read_bytes())
    for f in sorted(Path(__file__).parent.glob("*.py")):
        h.update(f.read_bytes())
    return h.hexdigest()[:24]


def _cache_dir() -> Path:
    import tempfile
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    for root in (Path(base) / "pmcal" / "plc_runtime", Path(tempfile.gettempdir()) / "pmcal-plc-runtime"):
        try:
            root.mkdir(parents=True, exist_ok=True)
            return root
        except OSError:
            continue
    return Path(tempfile.gettempdir())


def compile_project(folder: Path | str | None = None, *, cache: bool = True) -> Program:
    """Parse and compile a PLC project folder (default: the project's ``plc/``) with the library.

    Parsing with blark takes ~10 s; the compiled program is kept per process and on disk (keyed by
    the SHA-256 of the sources and of this package), so only the first run pays it.
    """
    if folder is None:
        import pmcal.plc
        folder = Path(pmcal.plc.__file__).parent
    return compile_files(project_files(Path(folder)), cache=cache)


def compile_files(files, *, cache: bool = True) -> Program:
    """Compile TwinCAT files and/or plain ``.st`` files (the library is added first)."""
    files = [LIBRARY, SYSTEM_INFO] + [Path(f) for f in files]
    key = _digest(files)
    with _CACHE_LOCK:
        if key in _CACHE:
            return _CACHE[key]
        path = _cache_dir() / f"{key}.pickle"
        prog = None
        if cache and path.exists():
            try:
                prog = pickle.loads(path.read_bytes())
            except Exception:   # a stale or truncated cache file: compile again
                prog = None
        if prog is None:
            prog = Compiler(parse_files(files, _cache_dir() if cache else None)).build()
            for pou in prog.pous.values():
                pou.unit = None
                for m in pou.methods.values():
                    m.unit = None
            if cache:
                try:
                    tmp = path.with_suffix(f".{os.getpid()}.tmp")
                    tmp.write_bytes(pickle.dumps(prog))
                    tmp.replace(path)
                except Exception:   # unwritable cache: same program, compiled again next time
                    pass
        prog.code = compile(prog.source, "<plc>", "exec")
        _CACHE[key] = prog
        return prog


class PlcRuntime:
    """A TwinCAT PLC runtime executing the compiled ST, one task, cycle by cycle.

    Parameters
    ----------
    program : Program, optional
        From :func:`compile_project` (default: the project's ``plc/``).
    task : sequence of str
        The PROGRAMs the task calls each cycle, in order.
    cycle_s : float
        Task cycle time (s); the simulated clock advances by it every cycle.
    library : dict, optional
        Replacements of library functions by name (e.g. a wrong ``F_DATA_TO_CRC16_CCITT`` to test
        the CRC self-test): ``callable(data: bytes, crc: int) -> int``.
    constants : dict, optional
        Values of scalar constants by ``"GVL.NAME"`` (another PLC project's parameters).
    trap_overflow : bool
        Stop the task on a floating-point overflow too (default False: the result is +-inf, see
        the package docstring).
    cpu : CpuModel
        The CPU whose time the work counters are turned into (default: the slowest of the CX5100/CX5200
        families, cost_model.CX_SLOWEST).

    Attributes
    ----------
    stopped : bool
        The task stopped on an exception (``fault`` says why); an ADS client sees the PLC not in RUN.
    work_last, work_max : dict
        Work of the last cycle and the largest per cycle since start: statements, math_calls
        (transcendental/numeric operator calls), bytes_copied (MEMCPY/MEMSET/MEMCMP/struct assignment),
        crc_bytes, cpu_cycles (the operations' clock cycles on the modelled CPU, cost_model.COSTS);
        ``calls_last``/``calls_max`` count calls per POU.
    task_us_last, task_us_max : float
        The task's own time (without the background PersistTask, which runs in a task of its own) in
        the last cycle and the most since start, µs on ``cpu`` (bridge/simulator/plc_runtime/cost_model.py).

    Examples
    --------
    >>> rt = PlcRuntime()                                         # doctest: +SKIP
    >>> rt.cycle(); rt.read_value("GVL_CompTable.stState.nCycle")  # doctest: +SKIP
    1
    """

    def __init__(self, program: Program | None = None, *, task=("PRG_CompTable",), cycle_s: float = 0.001,
                 library: dict | None = None, constants: dict | None = None, trap_overflow: bool = False,
                 persistent_write_cycles: int = 5, ams_port: int = 851, other_ports=(),
                 nc_lag_cycles: int = 2, move_cycles: int = 100, background=None,
                 cpu: CpuModel = CX_SLOWEST) -> None:
        if not cycle_s > 0:
            raise ValueError(f"cycle_s must be > 0, got {cycle_s}")
        self.program = program or compile_project()
        self.lock = threading.RLock()
        self.cycle_s = float(cycle_s)
        self.trap_overflow = trap_overflow
        self.persistent_write_cycles = int(persistent_write_cycles)
        self.ams_port = int(ams_port)                  # _AppInfo.AdsPort: 851 for the first runtime, 852 ...
        self.ams_ports = frozenset({self.ams_port, *other_ports})   # PLC runtimes on this device
        # axes (library AXIS_REF, MC_MoveAbsolute): NcToPlc shows a move nc_lag_cycles after its start (the
        # NC's own cycles; 2 ms SAF at a 1 ms task: 2), a modelled move lasts move_cycles
        self.nc_lag_cycles = int(nc_lag_cycles)
        self.move_cycles = int(move_cycles)
        self.library = {"F_DATA_TO_CRC16_CCITT": crc16_ccitt, **(library or {})}
        self.mem = bytearray(self.program.image)
        self.work_now = [0] * len(WORK)
        self.cpu = cpu
        self.task_us_last = 0.0                        # the task's (not the background's) modelled time, µs
        self.task_us_max = 0.0
        self.work_max = dict.fromkeys(WORK, 0)
        self.work_last = dict.fromkeys(WORK, 0)
        self.cycles = 0
        self.motion_idle = True
        self.fault: PlcFault | None = None
        p0, p1 = self.program.persistent
        self.saved_persistent = bytes(self.mem[p0:p1])
        self._task_names = tuple(task)
        # lower-priority tasks: (PROGRAM, every n task cycles), run after the task in those cycles; default:
        # the project's PersistTask (PRG_CompTableSave every 10 ms) if the program has it
        if background is None:
            background = ((SAVE_PROGRAM, SAVE_EVERY),) if SAVE_PROGRAM.lower() in self.program.pous else ()
        self._background_names = tuple((str(n), int(k)) for n, k in background)
        self._constants = dict(constants or {})
        self._exec_program()
        self._system_info()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _exec_program(self) -> None:
        """Load the program's generated code, its constants (with this runtime's overrides) and its task."""
        n = len(self.program.call_names)
        self.calls_now = [0] * n
        self.calls_max = dict.fromkeys(self.program.call_names, 0)
        self.calls_last = dict.fromkeys(self.program.call_names, 0)
        ns = make_helpers(self)
        ns["_CALLS"] = self.calls_now
        for key, (value, t, py) in self.program.constants.items():
            ns[py] = value
        self._ns = ns
        exec(self.program.code, ns)                    # noqa: S102 - our own generated code
        for key, value in self._constants.items():
            self.set_constant(key, value)
        self._task = []
        for name in self._task_names:
            pou = self.program.pous[name.lower()]
            self._task.append((ns[pou.pyname], self.program.instances[name.lower()]))
        self._background = []
        for name, every in self._background_names:
            pou = self.program.pous[name.lower()]
            self._background.append((ns[pou.pyname], self.program.instances[name.lower()], max(1, every)))

    # ---- execution ------------------------------------------------------------------------
    @property
    def clock_ms(self) -> int:
        """The task's time (ms): cycles completed x cycle time."""
        return int(round(self.cycles * self.cycle_s * 1000.0))

    @property
    def stopped(self) -> bool:
        return self.fault is not None

    def cycle(self) -> bool:
        """Run one task cycle; False if the task is stopped (now or before)."""
        with self.lock:
            if self.fault is not None:
                return False
            work, calls = self.work_now, self.calls_now
            work[:] = [0] * len(WORK)
            calls[:] = [0] * len(calls)
            try:
                for fn, addr in self._task:
                    fn(addr)
                self.task_us_last = self.cpu.micros(work[4], work[2] + work[3])   # cpu_cycles; copied + CRC bytes
                self.task_us_max = max(self.task_us_max, self.task_us_last)
                for fn, addr, every in self._background:
                    if self.cycles % every == every - 1:
                        fn(addr)
            except _TRAPS as exc:
                self.fault = PlcFault(getattr(exc, "kind", _kind(exc)), str(exc), self.cycles, self._where(exc))
            finally:
                self.cycles += 1
                for name, v in zip(WORK, work):
                    self.work_last[name] = v
                    if v > self.work_max[name]:
                        self.work_max[name] = v
                for name, v in zip(self.program.call_names, calls):
                    self.calls_last[name] = v
                    if v > self.calls_max[name]:
                        self.calls_max[name] = v
            return self.fault is None

    def run(self, cycles: int) -> int:
        """Run up to ``cycles`` cycles (fewer if the task stops); returns how many ran."""
        for i in range(cycles):
            if not self.cycle():
                return i
        return cycles

    def reset_work_max(self) -> None:
        with self.lock:
            self.work_max = dict.fromkeys(WORK, 0)
            self.calls_max = dict.fromkeys(self.program.call_names, 0)
            self.task_us_max = 0.0

    def overflow(self, x: float) -> float:
        if self.trap_overflow:
            raise PlcException("overflow", "floating-point overflow")
        return math.copysign(math.inf, x) if x == x else x

    def _where(self, exc: BaseException) -> str:
        tb = exc.__traceback__
        line = None
        while tb is not None:
            if tb.tb_frame.f_code.co_filename == "<plc>":
                line = tb.tb_lineno
            tb = tb.tb_next
        if line is None:
            return ""
        best = None
        for pyline, pou, stline in self.program.lines:
            if pyline <= line and (best is None or pyline >= best[0]):
                best = (pyline, pou, stline)
        return f"{best[1]} line {best[2]}" if best else ""

    # ---- the cyclic task in a thread ------------------------------------------------------
    def start(self, period_s: float | None = None, lifetime_s: float = 600.0, before=(), after=()) -> None:
        """Run :meth:`cycle` every ``period_s`` (default: the cycle time) in a daemon thread, with
        ``before``/``after`` hooks (the task's I/O mapping); ends by itself after ``lifetime_s``."""
        if self._thread is not None:
            return
        period = self.cycle_s if period_s is None else period_s
        self._stop.clear()
        deadline = time.monotonic() + lifetime_s

        def task() -> None:
            # a fixed-rate task: the next cycle starts one period after the last one started; a cycle
            # that overruns delays the following ones (at most 50 ms are caught up, then the
            # schedule restarts: like a TwinCAT task with exceed counter, simulated time stretches)
            due = time.monotonic()
            while not self._stop.is_set() and time.monotonic() < deadline:
                with self.lock:
                    if self.fault is None:
                        for hook in before:
                            hook()
                        if self.cycle():
                            for hook in after:
                                hook()
                due += period
                now = time.monotonic()
                if due > now:
                    self._stop.wait(due - now)
                else:
                    if now - due > 0.05:
                        due = now
                    time.sleep(0)                   # let clients (ADS, Modbus threads) in between cycles

        self._thread = threading.Thread(target=task, name="plc-runtime-task", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None

    # ---- remanent data: PERSISTENT and RETAIN ------------------------------------------------
    # What survives which event, as Infosys tc3_plc_intro "Remanent Variables - PERSISTENT, RETAIN"
    # (/content/1033/tc3_plc_intro/2528803467.html) and Tc2_Utilities "WritePersistentData"
    # (/content/1033/tcplclib_tc2_utilities/35068555.html) document it:
    #
    #   event                                   VAR      RETAIN (NovRam)   PERSISTENT
    #   restart (TwinCAT stop/start, UPS)       initial  kept              kept (written at shutdown)
    #   power cut without UPS                   initial  kept (NovRam)     as the last FB_WritePersistentData
    #   Reset cold                              initial  initial           kept
    #   download (persistent list unchanged)    initial  initial           kept, by name and type
    #   online change                           kept     kept              kept
    #   Reset origin                            initial  initial           initial (boot data deleted)
    #
    # A variable without an ADS symbol ({attribute 'hide'}) is in neither region (compiler): initial.
    def mark_persistent_saved(self) -> None:
        """What Tc2_Utilities FB_WritePersistentData completes: the PERSISTENT variables as they are now
        are what the next power-up restores."""
        p0, p1 = self.program.persistent
        self.saved_persistent = bytes(self.mem[p0:p1])

    def restart(self) -> None:
        """A clean restart (TwinCAT stop/start, or a power cycle with UPS): TwinCAT writes the
        PERSISTENT data at shutdown, so they survive; RETAIN data survive in NovRam; everything else
        starts from its initial value. The task must be stopped around it; a stopped task runs again."""
        with self.lock:
            self.mark_persistent_saved()
            self._power_up(keep_retain=True)

    warm_restart = restart

    def power_cut(self) -> None:
        """Power lost without UPS: RAM is gone, PERSISTENT data come back as the last
        FB_WritePersistentData (or clean shutdown) saved them; RETAIN data from NovRam."""
        with self.lock:
            self._power_up(keep_retain=True)

    def reset_cold(self) -> None:
        """Online command Reset cold: every variable but the PERSISTENT ones (as they are now) starts
        from its initial value, RETAIN included."""
        with self.lock:
            self.mark_persistent_saved()
            self._power_up(keep_retain=False)

    def reset_origin(self) -> None:
        """Online command Reset origin: everything starts from its initial value, PERSISTENT data too
        (their boot data are gone)."""
        with self.lock:
            p0, p1 = self.program.persistent
            self.saved_persistent = bytes(self.program.image[p0:p1])
            self._power_up(keep_retain=False)

    def online_change(self) -> None:
        """Online change of code that keeps every variable: nothing is reinitialised."""

    def download(self, program: Program) -> None:
        """Download of another program (the task stopped around it): PERSISTENT variables keep their
        values where the new program declares the same GVL variable with the same type size (TwinCAT
        checks the persistent list on download); everything else, RETAIN included, starts from the new
        program's initial values."""
        with self.lock:
            old, mem = self.program, bytes(self.mem)
            self.program = program
            self.mem = bytearray(program.image)
            for gvl, names in program.gvls.items():
                for name, gv in names.items():
                    was = old.gvls.get(gvl, {}).get(name)
                    if gv.persistent and was is not None and was.persistent and was.t.size == gv.t.size:
                        self.mem[gv.addr:gv.addr + gv.t.size] = mem[was.addr:was.addr + was.t.size]
            self._exec_program()
            self._system_info()
            self.mark_persistent_saved()
            self.fault = None

    def _power_up(self, keep_retain: bool) -> None:
        p0, p1 = self.program.persistent
        r0, r1 = self.program.retain
        retain = bytes(self.mem[r0:r1])
        self.mem[:] = self.program.image
        self.mem[p0:p1] = self.saved_persistent
        if keep_retain:
            self.mem[r0:r1] = retain
        self._system_info()
        self.fault = None

    def _system_info(self) -> None:
        """TwinCAT_SystemInfoVarList._AppInfo as TwinCAT fills it at start: this runtime's AMS port, the
        persistent boot data loaded."""
        if "twincat_systeminfovarlist" in self.program.gvls:
            self.write_value("TwinCAT_SystemInfoVarList._AppInfo.AdsPort", self.ams_port)
            self.write_value("TwinCAT_SystemInfoVarList._AppInfo.BootDataLoaded", True)

    # ---- variables by name ----------------------------------------------------------------
    def locate(self, path: str) -> tuple[int, DType]:
        """Address and type of a variable: ``GVL.name``, ``PRG.inst.member``, with ``[i, j]`` indices."""
        parts = re.findall(r"[A-Za-z_]\w*|\[[^\]]*\]", path)
        if not parts:
            raise KeyError(path)
        head = parts[0].lower()
        p = self.program
        if head in p.gvls:
            gv = p.gvls[head].get(parts[1].lower()) if len(parts) > 1 else None
            if gv is None:
                raise KeyError(path)
            addr, t, rest = gv.addr, gv.t, parts[2:]
        elif head in p.instances:
            addr, t, rest = p.instances[head], p.pous[head].itype, parts[1:]
        else:
            raise KeyError(path)
        for part in rest:
            if part.startswith("["):
                if t.kind != "array":
                    raise KeyError(path)
                idx = [int(x) for x in part[1:-1].split(",")]
                if len(idx) != len(t.dims):
                    raise KeyError(path)
                for i, (lo, hi), s in zip(idx, t.dims, strides(t)):
                    if not lo <= i <= hi:
                        raise KeyError(path)
                    addr += (i - lo) * s
                t = t.elem
            else:
                m = next((v for k, v in t.members.items() if k.lower() == part.lower()), None)
                if m is None:
                    raise KeyError(path)
                addr, t = addr + m[0], m[1]
        return addr, t

    def read_bytes(self, path: str) -> bytes:
        with self.lock:
            addr, t = self.locate(path)
            return bytes(self.mem[addr:addr + t.size])

    def write_bytes(self, path: str, data: bytes) -> None:
        with self.lock:
            addr, t = self.locate(path)
            if len(data) != t.size:
                raise ValueError(f"{path} is {t.size} bytes, got {len(data)}")
            self.mem[addr:addr + t.size] = data

    def read_value(self, path: str):
        with self.lock:
            addr, t = self.locate(path)
            if t.kind == "bool":
                return self.mem[addr] != 0
            if not t.scalar:
                raise TypeError(f"{path} is a {t.name}")
            return struct.unpack_from("<" + t.fmt, self.mem, addr)[0]

    def write_value(self, path: str, value) -> None:
        with self.lock:
            addr, t = self.locate(path)
            if t.kind == "bool":
                self.mem[addr] = 1 if value else 0
                return
            if not t.scalar:
                raise TypeError(f"{path} is a {t.name}")
            if t.kind in ("int", "enum", "pointer"):
                value = t.wrap(int(value))
            struct.pack_into("<" + t.fmt, self.mem, addr, value)

    def constant(self, key: str):
        """The value of a scalar constant (``"GVL.NAME"``) as the running program sees it."""
        k = key.lower()
        if k not in self.program.constants:
            raise KeyError(key)
        return self._ns[self.program.constants[k][2]]

    def set_constant(self, key: str, value) -> None:
        """Give a scalar constant (``"GVL.NAME"``) another value (array bounds stay compiled in)."""
        k = key.lower()
        if k not in self.program.constants:
            raise KeyError(key)
        _, t, py = self.program.constants[k]
        self._constants[key] = value                     # kept over a download of the same program
        self._ns[py] = float(value) if t.kind == "real" else value
        for name, memo in self._ns.items():           # pure functions may read constants
            if name.startswith("_MEMO_"):
                memo.clear()


def _kind(exc: BaseException) -> str:
    if isinstance(exc, ZeroDivisionError):
        return "division"
    if isinstance(exc, OverflowError):
        return "overflow"
    if isinstance(exc, ValueError):
        return "domain"
    return "access"
