"""The compensation-table PLC as the mocks and tests see it: :class:`PlcTwin`, the project's own ST
(``plc/``: PRG_CompTable with FB_CompTableManager, FB_CompTableCheck, FB_CompTableLookup) running on
:class:`~pmcal.bridge.simulator.plc_runtime.runtime.PlcRuntime`.

The symbols of GVL_CompTable are exchanged as bytes under the keys of
:data:`pmcal.bridge.plc_types.SYMBOLS` (the bytes are the PLC memory itself, in the DUTs' layout);
``motion_idle`` drives the simulated axes that PRG_CompTable reads (``AXIS_REF.ReadStatus``).
Nothing here decides anything about a table: every verdict comes from the ST.
"""

from __future__ import annotations

import time

import numpy as np

from pmcal.bridge.comptable import CompTable
from pmcal.bridge.nominal import NominalReference
from pmcal.bridge.simulator.plc_runtime.runtime import PlcRuntime
from pmcal.bridge.plc_types import SYMBOL, Header, PlcState, shadow_rows, used_values

GVL = "GVL_CompTable"
PRG = "PRG_CompTable"
#: the persistent double buffer (plc/GVLs/GVL_CompTableStore.TcGVL)
STORE = "GVL_CompTableStore"
#: GVL_CompTableParam constants that carry the nominal-IK reference geometry
_REFERENCE_CONSTANTS = ("REF_A_MM", "REF_H_MM", "REF_L_MM", "REF_PSI1_DEG", "REF_PSI2_DEG")
#: cycles seed() may run for the start-up check of the seeded table
SETTLE_CYCLES = 200_000


def machine_constants(machine: str, motors: int, corrections: bool) -> dict:
    """GVL_CompTableParam constants that pin what a PLC accepts: its machine, motors and table kind."""
    return {"GVL_CompTableParam.MACHINE": machine.encode("ascii"), "GVL_CompTableParam.NMOTORS": int(motors),
            "GVL_CompTableParam.CORRECTIONS": bool(corrections)}


def _time_setting(path: str, doc: str) -> property:
    """A TIME variable of the PLC as seconds, kept over restarts (the owner's configuration)."""
    def get(self) -> float:
        return self.runtime.read_value(path) / 1000.0

    def put(self, value: float) -> None:
        self._set(path, round(value * 1000.0))
    return property(get, put, doc=f"{path} (s): {doc}")


class PlcTwin:
    """The PLC side of the table hand-over and the motor-target lookup, executed from ``plc/``.

    Parameters
    ----------
    crc : callable, optional
        The PLC's ``F_DATA_TO_CRC16_CCITT(data: bytes, crc: int) -> int`` (default: Tc2_Utilities'
        semantics); another one models a wrong library.
    commit_timeout_s, staging_lease_s : float, optional
        PRG_CompTable.tCommitTimeout and FB_CompTableManager.tStagingLease (s).
    reference : NominalReference, optional
        GVL_CompTableParam.REF_*: the nominal geometry of F_CompTableNominalIk.
    cycle_s : float
        Task cycle time (s) of the simulated clock.
    runtime : PlcRuntime, optional
        An existing runtime (other parameters then only set its variables).
    machine, motors, corrections : optional
        What this PLC accepts, GVL_CompTableParam.MACHINE, NMOTORS and CORRECTIONS (set before the
        download on a real CX: plc/README.md); default: the OCPM (``ocpm_2dof``, 2 motors, motor
        commands). ``machine=""`` or ``motors=0`` is the shipped, unconfigured PLC (NOT_CONFIGURED).
    """

    def __init__(self, crc=None, commit_timeout_s: float | None = None, reference: NominalReference | None = None,
                 *, staging_lease_s: float | None = None, cycle_s: float = 0.001,
                 runtime: PlcRuntime | None = None, machine: str = "ocpm_2dof", motors: int = 2,
                 corrections: bool = False) -> None:
        library = {"F_DATA_TO_CRC16_CCITT": crc} if crc is not None else None
        constants = machine_constants(machine, motors, corrections)
        if reference is not None:
            constants.update({f"GVL_CompTableParam.{k}": v for k, v in zip(
                _REFERENCE_CONSTANTS, (reference.a_mm, reference.h_mm, reference.l_mm, reference.psi1_deg,
                                       reference.psi2_deg))})
        self.runtime = runtime or PlcRuntime(cycle_s=cycle_s, library=library, constants=constants)
        self.reference = reference or NominalReference.default()
        self.lock = self.runtime.lock
        self._settings: dict[str, int] = {}        # PLC variables set by the owner: kept over restarts
        if commit_timeout_s is not None:
            self.commit_timeout_s = commit_timeout_s
        if staging_lease_s is not None:
            self.staging_lease_s = staging_lease_s

    # ---- settings (PLC variables) ---------------------------------------------------------
    @property
    def motion_idle(self) -> bool:
        return self.runtime.motion_idle

    @motion_idle.setter
    def motion_idle(self, value: bool) -> None:
        self.runtime.motion_idle = bool(value)

    commit_timeout_s = _time_setting(f"{PRG}.tCommitTimeout", "a checked table not swapped in by then is dropped")
    staging_lease_s = _time_setting(f"{PRG}.fbManager.tStagingLease", "a silent staging owner loses the area after")

    def _set(self, path: str, value) -> None:
        self._settings[path] = value
        self.runtime.write_value(path, value)

    def _reapply(self) -> None:
        for path, value in self._settings.items():
            self.runtime.write_value(path, value)

    @property
    def commit_token(self) -> int:
        return self.runtime.read_value(f"{GVL}.nCommitToken")

    @property
    def use_modbus(self) -> bool:
        """PRG_CompTable.bUseModbus: FB_CompTableModbus maps the %M area (TF6250) onto GVL_CompTable."""
        return bool(self.runtime.read_value(f"{PRG}.bUseModbus"))

    @use_modbus.setter
    def use_modbus(self, value: bool) -> None:
        self._set(f"{PRG}.bUseModbus", bool(value))

    def modbus_memory(self, registers: int) -> np.ndarray:
        """The first ``registers`` WORDs of the PLC's %M area, as a writable view (TF6250 maps holding
        register 16#3000 + k onto %MW(2k))."""
        addr, size = self.runtime.program.m_area
        if 2 * registers > size:
            raise ValueError(f"%M holds {size // 2} registers, not {registers}")
        return np.frombuffer(self.runtime.mem, dtype="<u2", count=registers, offset=addr)

    @property
    def stopped(self) -> bool:
        return self.runtime.stopped

    @property
    def fault(self):
        return self.runtime.fault

    # ---- symbol access (what ADS / the Modbus mapping reach) ------------------------------
    def read_symbol(self, key: str) -> bytes:
        return self.runtime.read_bytes(f"{GVL}.{SYMBOL[key].st_name}")

    def write_symbol(self, key: str, data: bytes) -> None:
        """Write a symbol's bytes (sizes are checked by the transport, as the PLC would)."""
        sym = SYMBOL[key]
        if sym.written_by != "bridge":
            raise PermissionError(f"{key} is written by the PLC only")
        self.runtime.write_bytes(f"{GVL}.{sym.st_name}", bytes(data))

    def _shadow_addr(self) -> tuple[int, int]:
        addr, t = self.runtime.locate(f"{GVL}.aShadow")
        return addr, t.size

    def write_shadow_bytes(self, offset: int, data: bytes) -> None:
        """Bytes into ``aShadow`` at byte ``offset`` (the Modbus page adapter's store)."""
        with self.lock:
            addr, size = self._shadow_addr()
            if offset < 0 or offset + len(data) > size:
                raise ValueError("outside aShadow")
            self.runtime.mem[addr + offset:addr + offset + len(data)] = data

    def read_shadow_bytes(self, offset: int, size: int) -> bytes:
        with self.lock:
            addr, total = self._shadow_addr()
            if offset < 0 or offset + size > total:
                raise ValueError("outside aShadow")
            return bytes(self.runtime.mem[addr + offset:addr + offset + size])

    def corrupt_shadow(self) -> None:
        """Flip the lowest mantissa bit of the first staged value (fault injection: memory error)."""
        with self.lock:
            addr, _ = self._shadow_addr()
            self.runtime.mem[addr] ^= 0x01

    def corrupt_persistent(self) -> None:
        """Flip a bit of the active table in persistent memory (fault injection for the start-up check)."""
        with self.lock:
            addr, _ = self.runtime.locate(f"{STORE}.aBuffer[{self._active()}]")
            self.runtime.mem[addr + 3] ^= 0x10
            self.runtime.mark_persistent_saved()

    # ---- observation ----------------------------------------------------------------------
    def _active(self) -> int:
        return self.runtime.read_value(f"{STORE}.nActive")

    @property
    def state(self) -> PlcState:
        return PlcState.unpack(self.read_symbol("state"))

    @property
    def cycle_count(self) -> int:
        return self.runtime.cycles

    def active_table(self) -> tuple[Header, np.ndarray]:
        """Header and used values (copy) of the active buffer."""
        with self.lock:
            k = self._active()
            h = Header.unpack(self.runtime.read_bytes(f"{STORE}.aHeader[{k}]"))
            data = self.runtime.read_bytes(f"{STORE}.aBuffer[{k}]")
            return h, used_values(h, np.frombuffer(data, dtype="<f8")).copy()

    # ---- the PLC task ---------------------------------------------------------------------
    def cycle(self) -> bool:
        """One task cycle; False if the task is stopped."""
        return self.runtime.cycle()

    def start(self, period_s: float | None = None, lifetime_s: float = 600.0, before=(), after=()) -> None:
        self.runtime.start(period_s, lifetime_s, before=before, after=after)

    def stop(self) -> None:
        self.runtime.stop()

    def restart(self) -> None:
        """A clean restart (TwinCAT writes PERSISTENT data at shutdown): the double buffer, its headers
        and ``nActive`` survive, everything else starts from its initial value; FB_CompTableManager
        then re-checks the active table over its first cycles."""
        with self.lock:
            self.runtime.restart()
            self._reapply()

    def power_cut(self) -> None:
        """Power lost without UPS: PERSISTENT data as the last FB_WritePersistentData saved them."""
        with self.lock:
            self.runtime.power_cut()
            self._reapply()

    def reset_cold(self) -> None:
        """Online command Reset cold: PERSISTENT data stay, everything else (RETAIN too) is initial."""
        with self.lock:
            self.runtime.reset_cold()
            self._reapply()

    def download(self, program=None) -> None:
        """Download of ``program`` (default: the same one again): PERSISTENT data stay where the new
        program declares them alike (:meth:`PlcRuntime.download`)."""
        with self.lock:
            self.runtime.download(program or self.runtime.program)
            self._reapply()

    def configure(self, machine: str, motors: int, corrections: bool) -> None:
        """Set what this PLC accepts (GVL_CompTableParam.MACHINE, NMOTORS, CORRECTIONS): on a real CX
        an edit of the GVL and a download; here the constants change and the PLC restarts (the table
        store stays, the start-up check applies the new configuration; the memory stays the same
        object, so a running mock's views of it stay valid)."""
        with self.lock:
            for key, value in machine_constants(machine, motors, corrections).items():
                self.runtime.set_constant(key, value)
            self.restart()

    def configure_for(self, table: CompTable) -> None:
        """:meth:`configure` for the machine, motors and kind of ``table``."""
        from pmcal.bridge.nominal import REFERENCE_CONTROLLER

        self.configure(table.machine, table.n_motors, table.reference_code == REFERENCE_CONTROLLER)

    def has_symbol(self, key: str) -> bool:
        """The PLC program generates an ADS symbol for this GVL_CompTable variable (declared, and not
        {attribute 'hide'}: Infosys tc3_plc_intro, Attribute 'hide')."""
        gv = self.runtime.program.gvls.get(GVL.lower(), {}).get(SYMBOL[key].st_name.lower())
        return gv is not None and not gv.hidden

    @property
    def started(self) -> bool:
        """FB_CompTableManager finished its start-up check of the persistent table (lookups may use it)."""
        return bool(self.runtime.read_value(f"{GVL}.bActiveChecked"))

    def wait_started(self, timeout_s: float = 10.0) -> bool:
        """Wait (wall clock, the task thread running) until :attr:`started` or the task stopped."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.started or self.stopped:
                return self.started
            time.sleep(0.002)
        return False

    def seed(self, table: CompTable) -> None:
        """Commissioning: make ``table`` the active table in persistent memory (as if it had been
        committed and saved before), restart the PLC and run the start-up check to its end."""
        rt = self.runtime
        with self.lock:
            idx = 1 - self._active()
            addr, t = rt.locate(f"{STORE}.aBuffer[{idx}]")
            rows = shadow_rows(table)
            rt.mem[addr:addr + t.size] = rows + bytes(t.size - len(rows))
            rt.write_bytes(f"{STORE}.aHeader[{idx}]", Header.of(table).pack())
            rt.write_value(f"{STORE}.nActive", idx)
            rt.restart()
            self._reapply()
            for _ in range(SETTLE_CYCLES):
                if not rt.cycle() or self.started:
                    break
