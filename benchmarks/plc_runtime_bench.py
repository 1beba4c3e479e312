"""Cost of the shipped ST per task cycle, as the interpreter (bridge/simulator/plc_runtime) counts and times it.

For a commit of a 37 x 13 and a 100 x 100 table (nominal-IK reference, the project's default) and of a
Delta-shaped 13 x 13 x 9 table (3 motors, corrections to the controller's IK) on a PLC configured for
that machine that already holds a table of the same grid: the task cycles the commit takes, and per cycle the
most statements, numeric operator calls (SIN, COS, SQRT, ACOS, ATAN2...), calls of the nominal IK
F_CompTableNominalIk, bytes copied (MEMCPY / struct assignment) and CRC bytes; the interpreter's own
time: CPU per idle cycle (median), CPU of the whole commit (process time,
so other load on the machine does not count). The cold-start compile (blark parse) is not included.
Then the task's modelled time per cycle on the slowest CX5100/CX5200-class CPU (cost model with its
sources: bridge/simulator/plc_runtime/cost_model.py): the worst and the median cycle of the commit in µs against the
share of the 1 ms cycle the table manager may take (TASK_SHARE).

Run: python benchmarks/plc_runtime_bench.py [--idle 2000] [--json PATH]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import print_table, write_json  # noqa: E402

from pmcal.bridge.simulator.plc_runtime import PlcTwin  # noqa: E402
from pmcal.bridge.simulator.plc_runtime.cost_model import CX_SLOWEST, TASK_SHARE  # noqa: E402
from tests.bridge_fixtures import commit_on_twin, delta_correction_table, make_table  # noqa: E402

IK = "F_CompTableNominalIk"
TOKEN = 0x800D0001          # the staging token of the benchmark's client


def ocpm_table(n_phi: int, n_theta: int):
    """The OCPM's table on an n_phi x n_theta grid: ``make(version, offset_deg)``."""
    return lambda version, offset: make_table(version=version, n_phi=n_phi, n_theta=n_theta, offset_deg=offset)


def commit_cost(label: str, make) -> dict:
    plc = PlcTwin()
    plc.configure_for(make(1, 0.0))
    plc.seed(make(1, 0.0))
    rt = plc.runtime
    t0 = time.process_time()
    st, modelled = commit_on_twin(plc, make(2, 0.1), TOKEN)
    total = time.process_time() - t0
    share = TASK_SHARE * 1e6 * rt.cycle_s
    return {"grid": label, "status": st.status.name if hasattr(st.status, "name") else st.status,
            "cycles": len(modelled), **{f"max_{k}": v for k, v in rt.work_max.items()},
            "max_ik_calls": rt.calls_max[IK], "commit_cpu_s": total,
            "worst_cycle_us": max(modelled), "median_cycle_us": statistics.median(modelled),
            "share_us": share, "within_share": max(modelled) <= share}


def idle_cost(n: int) -> float:
    plc = PlcTwin()
    plc.seed(make_table(version=1))
    times = []
    for _ in range(n):
        a = time.process_time()
        plc.cycle()
        times.append(time.process_time() - a)
    return 1e6 * statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--idle", type=int, default=2000, help="idle cycles timed (count)")
    ap.add_argument("--json", default=None, help="output file (default benchmarks/results/plc_runtime_bench.json)")
    args = ap.parse_args()
    rows = [commit_cost("37x13", ocpm_table(37, 13)), commit_cost("100x100", ocpm_table(100, 100)),
            commit_cost("13x13x9 (Delta, 3 motors)", delta_correction_table)]
    idle_us = idle_cost(args.idle)
    keys = ["grid", "status", "cycles", "max_statements", "max_math_calls", "max_ik_calls", "max_bytes_copied",
            "max_crc_bytes", "commit_cpu_s"]
    print_table("Commit of a table on the interpreted ST (per task cycle: the largest)", keys,
                [[r[k] for k in keys] for r in rows])
    keys = ["grid", "max_cpu_cycles", "worst_cycle_us", "median_cycle_us", "share_us", "within_share"]
    print_table(f"Modelled task time per cycle on {CX_SLOWEST.name} (bridge/simulator/plc_runtime/cost_model.py)", keys,
                [[r[k] for k in keys] for r in rows])
    print(f"\nidle cycle (PRG_CompTable, no commit, no lookup): {idle_us:.1f} us CPU (median of {args.idle})")
    write_json("plc_runtime_bench", {"commit": rows, "idle_cycle_cpu_us": idle_us, "cpu_model": CX_SLOWEST.name,
                                     "clock_hz": CX_SLOWEST.clock_hz, "task_share": TASK_SHARE}, args.json)


if __name__ == "__main__":
    main()
