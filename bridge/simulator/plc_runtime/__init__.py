"""An executable, cycle-by-cycle model of the project's TwinCAT 3 ST (``plc/``): the PLC the mocks serve.

Pipeline: :mod:`.source` parses the ``.TcPOU/.TcDUT/.TcGVL`` files (and ``library.st``, the library
POUs written in ST) with blark; :mod:`.compiler` lays out every variable in one byte array (the DUT
layouts of :mod:`.datatypes`) and translates every POU body and method into a Python function;
:mod:`.runtime` runs the task (``PRG_CompTable``) cycle by cycle; :mod:`.comptable_plc` offers the
compensation-table view the mock servers and tests use (:class:`PlcTwin`, the interface of the former
hand transliteration it replaced: symbol keys of :data:`pmcal.bridge.plc_types.SYMBOLS`).
The compiled program is cached per process and on disk (``~/.cache/pmcal/plc_runtime``, keyed by
the SHA-256 of the sources): only the first run pays blark's ~10 s.

TwinCAT semantics modelled, and where they come from
----------------------------------------------------
- **LREAL** is an IEEE-754 double (Python float); REAL is rounded to single precision when stored.
- **Floating-point exceptions stop the task** (Infosys, TE1420 "Exception Handling": "Default setting
  in TwinCAT is that at divide-by-zero and invalid-operation the execution of the program is stopped";
  TC3 PLC "DIV": "division by zero always leads to an exception and the corresponding task is
  stopped"; TF3600 "NaN values": "comparisons with NaN can lead to an exception"). Modelled: a
  division by zero (integer or real, also ``MOD``), a real arithmetic result that is NaN (checked
  where the value is stored, passed to a call or compared; so ``x := 1.0/0.0*0.0`` and ``inf - inf``
  stop), an ordered or equality comparison with a NaN operand, SQRT/LN/LOG/ASIN/ACOS outside their
  domain, NaN or infinity converted to an integer. Copying a NaN (assignment, MEMCPY, a UNION) is not
  arithmetic and does not stop. Stricter than x86 SSE in two corners, deliberately: ``=``/``<>`` with
  a NaN operand also stop (UCOMISD would not signal a quiet NaN), and arithmetic on a quiet NaN read
  from memory stops (SSE propagates it silently); a program that passes here passes on the target.
- **Overflow does not stop** (overflow is not among the default exceptions above): the result is
  +-inf, as IEEE-754 with the overflow exception masked. ``PlcRuntime(trap_overflow=True)`` stops.
- **Integers wrap** to the width of the variable they are stored in (two's complement, SINT..LINT,
  USINT..ULINT, BYTE..LWORD); intermediate results are exact, as in the x64 target's 64-bit registers,
  and are truncated only when stored (Infosys tc3_plc_intro, Operators): ``NOT`` of a UDINT or WORD has
  its upper register bits set, so ``a = NOT b`` is FALSE (write ``(a XOR b) = 16#FFFFFFFF``); conversions
  ``*_TO_*`` wrap, real-to-integer conversions round to nearest even, TRUNC truncates toward zero.
- **Short-circuit**: AND/OR/XOR evaluate both operands (IEC 61131-3); AND_THEN/OR_ELSE short-circuit.
- **TIME** is an unsigned 32-bit count of milliseconds; ``TIME()`` in TON reads the **simulated
  clock**: completed cycles x cycle time (default 1 ms), never the wall clock.
- **PERSISTENT** variables (``VAR_GLOBAL PERSISTENT``) survive :meth:`PlcRuntime.restart` (TwinCAT
  writes persistent data at a clean shutdown), a Reset cold and a download; :meth:`PlcRuntime.power_cut`
  restores them as the last Tc2_Utilities ``FB_WritePersistentData`` (or clean shutdown) saved them;
  only a Reset origin clears them. **RETAIN** variables survive a restart and a power cut (NovRam) but
  not a Reset cold or a download (Infosys tc3_plc_intro, "Remanent Variables - PERSISTENT, RETAIN").
  A variable under ``{attribute 'hide'}`` (or 'TcNoSymbol') is neither: TwinCAT cannot save it as
  persistent and generates no ADS symbol for it (Infosys tc3_plc_intro, Attribute 'hide'); the mocks
  do not serve it. The FB is modelled (``library.st``): a rising START makes it BUSY for
  ``persistent_write_cycles`` cycles (default 5), then it saves the persistent variables as they are at
  that moment, if PORT is this runtime's AMS port (``TwinCAT_SystemInfoVarList._AppInfo.AdsPort``).
- **Axes** (``AXIS_REF``, ``MC_MoveAbsolute``): a move started in the PLC shows in the NcToPlc status
  ``nc_lag_cycles`` task cycles later, as the NC picks it up in its own cycles.
- **Memory**: every variable has an address; ADR, pointers, REFERENCE TO (``REF=``), MEMCPY/MEMSET/
  MEMCMP work on the one byte array (an address outside it, or NULL, stops the task: a page fault);
  an array index outside its bounds stops the task (TwinCAT would read foreign memory or raise an
  access violation; the interpreter refuses to guess).
- **ADS consistency**: symbol reads and writes through :class:`PlcTwin` take the runtime's lock, so a
  client sees the memory between two cycles, never in the middle of one (ADS "consistent data
  exchange", Infosys TC3 ADS introduction).

Supported ST subset
-------------------
PROGRAM, FUNCTION_BLOCK (VAR_INPUT/OUTPUT/IN_OUT/VAR, initial values), FUNCTION (with VAR_OUTPUT),
METHOD (return value, VAR_INPUT/IN_OUT/VAR, implicit THIS), VAR CONSTANT, GVLs (qualified access,
CONSTANT, PERSISTENT), located variables ``AT %MBn`` (the %M area), STRUCT with ``pack_mode``,
UNION, enums (qualified values, base type; ``{attribute 'strict'}`` enforced: no arithmetic on such an
enum, no other constant and no value of another type assigned to it, as TwinCAT's compile errors),
ARRAY (multi-dimensional, ARRAY OF ARRAY, of structs),
STRING(n), POINTER TO, REFERENCE TO; statements :=, REF=, IF/ELSIF/ELSE, CASE (values, ranges,
enum values), FOR (constant BY), WHILE, REPEAT, EXIT, RETURN, calls with named/positional inputs
and ``=>`` outputs; the operators and library functions listed in
:data:`pmcal.bridge.simulator.plc_runtime.builtins.BUILTINS` (each with its Beckhoff document), R_TRIG,
F_TRIG, TON, AXIS_REF (Status read from :attr:`PlcRuntime.motion_idle`), FB_WritePersistentData.
Not supported (a :class:`~pmcal.bridge.simulator.plc_runtime.compiler.PlcCompileError` names the POU):
EXTENDS/IMPLEMENTS, interfaces, properties, actions, CONTINUE, JMP, VAR_INST, VAR_STAT, RETAIN or
PERSISTENT outside a GVL, string functions (LEN, CONCAT...), recursion (frames are static),
the address of a scalar function local whose address is never taken with ADR (it lives in a Python
local). Non-TwinCAT names (ATAN2) run but are listed in ``Program.nonstandard``.

Speed: a FUNCTION that reads only its inputs, locals and constants (F_CompTableNominalIk,
F_CompTableIsFinite) is evaluated once per distinct input and the cached result is returned with the
work the evaluation counted, so results and counters equal a real call.

Work counters per cycle (:attr:`PlcRuntime.work_last` / ``work_max``): statements executed, numeric
operator calls (SQRT, SIN, ..., EXPT, ATAN2), bytes copied (MEMCPY/MEMSET/struct and array
assignment), bytes run through a CRC; calls per POU (``calls_last``/``calls_max``).

Example
-------
>>> from pmcal.bridge.simulator.plc_runtime import PlcTwin        # doctest: +SKIP
>>> plc = PlcTwin(); plc.cycle(); plc.state.cycle         # doctest: +SKIP
1
"""

from pmcal.bridge.simulator.plc_runtime.builtins import PlcException
from pmcal.bridge.simulator.plc_runtime.runtime import PlcFault, PlcRuntime, compile_files, compile_project
from pmcal.bridge.simulator.plc_runtime.comptable_plc import PlcTwin  # noqa: E402  (needs the runtime)

__all__ = ["PlcException", "PlcFault", "PlcRuntime", "PlcTwin", "compile_files", "compile_project"]
