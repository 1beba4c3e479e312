"""Twin in the loop of a machine folder (``pmcal --machine DIR loop``, pmcal/apps/chain_loop.py) over both
transports and several seeds: the task site's position error at held-out targets inside the table's grid
before the push (nominal table: the controller's nominal IK), after it (nominal IK + the PLC's looked-up
correction), and with the identified machine's own IK (no table); true (the twin's) and as the tracker
measures it (rigid fit of the nests); and the time of one loop (calibration: planned campaign,
identification, table; then mock PLC, lookups, push, lookups).

Run: python benchmarks/chain_loop_bench.py [--machine delta_3dof] [--seeds 5] [--targets 24] [--json PATH]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import print_table, write_json  # noqa: E402
from pmcal.apps.chain_loop import calibrate, run_chain_loop  # noqa: E402
from pmcal.apps.twin_loop import loopback_mock  # noqa: E402
from pmcal.machines import Machine  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--machine", default="delta_3dof", help="built-in name or machine folder")
    ap.add_argument("--seeds", type=int, default=5, help="seeds 1..N of the errors, campaign and targets")
    ap.add_argument("--targets", type=int, default=24, help="held-out targets per loop")
    ap.add_argument("--json", default=None, help="output JSON (default benchmarks/results/chain_loop_bench.json)")
    args = ap.parse_args(argv)
    machine = Machine.resolve(args.machine)
    machine.twin                                               # compiled once, outside the timings
    rows, runs = [], []
    for seed in range(1, args.seeds + 1):
        t0 = time.perf_counter()
        cal = calibrate(machine, seed=seed)
        t_cal = time.perf_counter() - t0
        for transport in ("ads", "modbus"):
            t1 = time.perf_counter()
            with loopback_mock(transport) as mock:
                res = run_chain_loop(mock, machine, cal, n_targets=args.targets, seed=seed)
            t_loop = time.perf_counter() - t1
            s = res.summary()
            runs.append({"seed": seed, "calibration_s": t_cal, "loop_s": t_loop, **s})
            rows.append([seed, transport, s["before"]["true_rms_mm"], s["before"]["true_max_mm"],
                         s["after"]["true_rms_mm"], s["after"]["true_max_mm"], s["direct_no_table"]["true_rms_mm"],
                         s["direct_no_table"]["true_max_mm"], s["after"]["rms_mm"], s["direct_no_table"]["rms_mm"],
                         t_cal, t_loop, str(s["plc_equals_table_lookup"])])
    header = ["seed", "transport", "before rms", "before max", "after rms", "after max", "direct rms",
              "direct max", "after rms (tracker)", "direct rms (tracker)", "calibration s", "loop s",
              "PLC = lookup"]
    print_table(f"{machine.name}: twin in the loop, {args.targets} held-out targets inside the table's grid, "
                "true position error of the task site (mm) unless marked", header, rows)

    def med(key, state=None, field=None):
        vals = [r[key] if state is None else r[state][field] for r in runs]
        return float(np.median(vals))

    summary = {k: med(k) for k in ("calibration_s", "loop_s")}
    for state in ("before", "after", "direct_no_table"):
        for f in ("true_rms_mm", "true_max_mm", "rms_mm"):
            summary[f"{state}_{f}_median"] = med(None, state, f)
    print_table("medians over seeds and transports", list(summary), [list(summary.values())])
    write_json("chain_loop_bench", {"machine_name": machine.name, "targets": args.targets, "seeds": args.seeds,
                                    "median": summary, "runs": runs}, args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
