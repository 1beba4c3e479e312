"""Cost of the shipped ST per task cycle, as the interpreter (bridge/plc_runtime) counts and times it.

For a commit of a 37 x 13 and a 100 x 100 table (nominal-IK reference, the project's default) and of a
Delta-shaped 13 x 13 x 9 table (3 motors, corrections to the controller's IK) on a PLC configured for
that machine that already holds a table of the same grid: the task cycles the commit takes, and per cycle the
most statements, numeric operator calls (SIN, COS, SQRT, ACOS, ATAN2...), calls of the nominal IK
F_CompTableNominalIk, bytes copied (MEMCPY / struct assignment) and CRC bytes; the interpreter's own
time: CPU per idle cycle (median), CPU of the busiest cycle, CPU of the whole commit (process time,
so other load on the machine does not count). The cold-start compile (blark parse) is not included.

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
import numpy as np  # noqa: E402

from pmcal.bridge import plc_types  # noqa: E402
from pmcal.bridge.comptable import Axis, CompTable, Motor  # noqa: E402
from pmcal.bridge.plc_runtime import PlcTwin  # noqa: E402
from pmcal.bridge.plc_types import Header, State, shadow_rows  # noqa: E402
from tests.bridge_fixtures import make_table  # noqa: E402

IK = "F_CompTableNominalIk"
TOKEN = 0x800D0001          # the staging token of the benchmark's client


def ocpm_table(n_phi: int, n_theta: int):
    """The OCPM's table on an n_phi x n_theta grid: ``make(version, offset_deg)``."""
    return lambda version, offset: make_table(version=version, n_phi=n_phi, n_theta=n_theta, offset_deg=offset)


def delta_table(version: int, offset: float):
    """A Delta-shaped table: 13 x 13 x 9 nodes over x, y, z (mm), 3 revolute motors, corrections to the
    controller's IK (nReference 2) of at most 0.3 deg, as mjcf/delta_3dof's default [table]."""
    axes = [Axis("x", "mm", -150.0, 150.0, 13), Axis("y", "mm", -150.0, 150.0, 13), Axis("z", "mm", -900.0, -700.0, 9)]
    motors = [Motor(f"m{k + 1}", "deg", -1.0, 1.0, 0.5) for k in range(3)]
    shape = (13, 13, 9, 3)
    x = CompTable(machine="delta_3dof", version=1, axes=axes, motors=motors, values=np.zeros(shape)).nodes()
    values = 0.2 * np.sin(x / 80.0) + offset
    return CompTable(machine="delta_3dof", version=version, axes=axes, motors=motors, values=values,
                     reference="controller").validate()


def commit_cost(label: str, make) -> dict:
    plc = PlcTwin()
    plc.configure_for(make(1, 0.0))
    plc.seed(make(1, 0.0))
    rt = plc.runtime
    table = make(2, 0.1)
    rows = shadow_rows(table)
    plc.write_symbol("staging_claim", TOKEN.to_bytes(4, "little"))
    plc.cycle()                                            # the claim is granted
    plc.write_symbol("shadow_header", Header.of(table).pack())
    plc.write_symbol("shadow", rows + bytes(plc_types.SHADOW_SIZE - len(rows)))
    rt.reset_work_max()
    plc.write_symbol("commit", TOKEN.to_bytes(4, "little"))
    cycles, busiest, t0 = 0, 0.0, time.process_time()
    while True:
        a = time.process_time()
        plc.cycle()
        busiest = max(busiest, time.process_time() - a)
        cycles += 1
        st = plc.state
        if plc.stopped or (st.ack_token == TOKEN and st.state == State.IDLE):
            break
        if cycles == 1 and st.state != State.CHECKING:
            break
    total = time.process_time() - t0
    return {"grid": label, "status": st.status.name if hasattr(st.status, "name") else st.status,
            "cycles": cycles, **{f"max_{k}": v for k, v in rt.work_max.items()},
            "max_ik_calls": rt.calls_max[IK], "busiest_cycle_cpu_ms": 1e3 * busiest, "commit_cpu_s": total}


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
            commit_cost("13x13x9 (Delta, 3 motors)", delta_table)]
    idle_us = idle_cost(args.idle)
    keys = ["grid", "status", "cycles", "max_statements", "max_math_calls", "max_ik_calls", "max_bytes_copied",
            "max_crc_bytes", "busiest_cycle_cpu_ms", "commit_cpu_s"]
    print_table("Commit of a table on the interpreted ST (per task cycle: the largest)", keys,
                [[r[k] for k in keys] for r in rows])
    print(f"\nidle cycle (PRG_CompTable, no commit, no lookup): {idle_us:.1f} us CPU (median of {args.idle})")
    write_json("plc_runtime_bench", {"commit": rows, "idle_cycle_cpu_us": idle_us}, args.json)


if __name__ == "__main__":
    main()
