"""What one task cycle of the shipped ST costs on a CX5100/CX5200-class CPU: a per-operation cost model.

The interpreter charges every operation it executes with the clock cycles the modelled CPU needs for it
(:data:`COSTS`, added up while the ST is compiled, per statement and per evaluated condition) and turns
the work it counts at run time (bytes copied, CRC bytes) into cycles at :data:`COPY_BYTES_PER_CYCLE`;
:meth:`CpuModel.micros` gives the task's time in µs. The test ``tests/test_plc_cost.py`` fails when the
busiest cycle of a commit exceeds :data:`TASK_SHARE` of the 1 ms task cycle, and
``benchmarks/plc_runtime_bench.py`` prints the figures.

Sources and decisions
---------------------
* **The CPUs** (Beckhoff Infosys, CX5100 and CX5200 manuals, technical data): CX5120 Intel Atom E3815
  1.46 GHz (1 core), CX5130 E3827 1.75 GHz (2 cores), CX5140 E3845 1.91 GHz (4 cores): Silvermont cores
  (Bay Trail); CX5220 Atom E3930 1.3 GHz (2 cores), CX5230 E3940 1.6 GHz, CX5240 E3950 1.6 GHz: Goldmont
  cores (Apollo Lake). The model takes the slowest clock of both families, **1.3 GHz** (CX5220), with
  the Silvermont latencies below (Goldmont's are the same or shorter).
* **The cost per operation** is the instruction's *latency* (not its throughput) from Agner Fog,
  "Instruction tables: lists of instruction latencies, throughputs and micro-operation breakdowns for
  Intel, AMD and VIA CPUs", section Intel Silvermont, rounded up: register ALU operation 1, integer
  multiply 5 (IMUL r64), integer divide 90 (DIV/IDIV r64: 25-87), load from the L1 cache 3 (MOV r,m),
  store 1, LREAL add/subtract 3 (ADDSD), multiply 5 (MULSD), divide and square root 40 (DIVSD, SQRTSD:
  up to 34-40), compare 4 (UCOMISD and SETcc), conversion between integer and LREAL 7 (CVTSI2SD,
  CVTTSD2SI). A load through a computed address (an array element with a variable index, a pointer
  target: the table data, which does not fit the 24 KB L1 data cache) costs an L2 hit, 16 (Intel 64 and
  IA-32 Architectures Optimization Reference Manual, Silvermont: L2 latency 14, rounded up). A branch
  costs its misprediction, 14 (Agner Fog, "The microarchitecture of Intel, AMD and VIA CPUs", Silvermont:
  misprediction penalty about 10-11, rounded up), except a loop's back edge, which is predicted (1) and
  mispredicted once at the exit. A transcendental operator (SIN, COS, TAN, ASIN, ACOS, ATAN, ATAN2, EXP,
  LN, LOG, EXPT) costs 200 (x87 FSIN/FCOS/FPATAN on Silvermont: up to about 180-190; a library routine is
  of the same order), a call 20 (CALL, RET, frame set-up and the argument stores, counted on top).
  Copying (MEMCPY, struct assignment) and CRC bytes counted at run time: 1 byte per cycle (REP MOVSB
  streams 8-16 bytes per cycle from L1; 1 is a bound for data from L2 or memory).
* **Why latencies add**: TwinCAT's code generator keeps variables in memory between statements, so most
  operations of a statement form one dependency chain; adding the latencies of every operation, with no
  overlap on the two-wide out-of-order core, is an upper bound for the cycle, which is what a budget
  check wants. Not modelled: the task's own overhead (I/O mapping, the ADS router), other tasks of the
  same core preempting it, cache misses to DRAM (the table, 2 x 160 KB, stays in the 1-2 MB L2 between
  cycles unless other tasks evict it) and TwinCAT's implicit checks (CheckBounds and friends, off by
  default).
* **The share** (decision): the table manager runs inside the motion task beside the machine's own code,
  so at its busiest it may take a quarter of a 1 ms cycle (:data:`TASK_SHARE`, 250 µs); the rest is the
  machine's.
"""

from __future__ import annotations

from dataclasses import dataclass

#: clock cycles per operation on the modelled core (Silvermont latencies, rounded up; see the docstring)
COSTS = {
    "alu": 1,             # integer/bit/boolean operation, register move, shift, negation
    "int_mul": 5,
    "int_div": 90,        # also MOD
    "load": 3,            # a variable at a fixed address (L1)
    "load_far": 16,       # through a computed address: array element with a variable index, pointer target (L2)
    "store": 1,
    "index": 7,           # variable index: bound subtraction, multiply by the stride, add (1 + 5 + 1)
    "fp_add": 3,
    "fp_mul": 5,
    "fp_div": 40,         # also SQRT and REAL MOD
    "fp_cmp": 4,
    "convert": 7,         # integer <-> LREAL, TRUNC
    "branch": 14,         # a data-dependent branch: its misprediction
    "loop": 1,            # a loop's predicted back edge (its exit is charged a branch)
    "transcendental": 200,
    "call": 20,
}
#: bytes copied (MEMCPY, struct assignment) or CRC'd by a library function per clock cycle
COPY_BYTES_PER_CYCLE = 1.0
#: the share of the 1 ms task cycle the table manager may take at its busiest (a decision, see above)
TASK_SHARE = 0.25


@dataclass(frozen=True)
class CpuModel:
    """A PLC CPU: its name and clock (Hz). Costs per operation: :data:`COSTS` (cycles)."""

    name: str
    clock_hz: float

    def micros(self, cpu_cycles: float, bytes_moved: float) -> float:
        """The task's time in µs on this CPU for ``cpu_cycles`` of its statements' operations (the work counter
        ``cpu_cycles``) and ``bytes_moved`` bytes copied and CRC'd at :data:`COPY_BYTES_PER_CYCLE`."""
        return (cpu_cycles + bytes_moved / COPY_BYTES_PER_CYCLE) / self.clock_hz * 1e6


#: the slowest CPU of the CX5100/CX5200 families (CX5220: Atom E3930, 1.3 GHz, Goldmont)
CX_SLOWEST = CpuModel("CX5220 (Atom E3930, 1.3 GHz; Silvermont latencies)", 1.3e9)
