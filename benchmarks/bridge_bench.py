"""Bridge speed: push + read-back + commit + acknowledgement of a 100x100x2 LREAL table over ADS and
Modbus TCP against the mock PLCs on loopback (real pyads / pymodbus clients and servers, PLC task at
1 ms), and the twin-in-the-loop pointing error before and after a push.

Targets (issue 5): ADS <= 50 ms, Modbus <= 1 s for the whole hand-over of a 100x100x2 table.

Run: python benchmarks/bridge_bench.py [--repeat-ads 20] [--repeat-modbus 5] [--no-loop] [--json PATH]
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import print_table, write_json  # noqa: E402
from pmcal.bridge.ads import AdsLink, set_adslib_log_level  # noqa: E402
from pmcal.bridge.ads_mock import AdsMockPlc  # noqa: E402
from pmcal.apps.plc_loop import DEFAULT_GRID, run_loop  # noqa: E402
from pmcal.bridge.modbus import ModbusLink  # noqa: E402
from pmcal.bridge.modbus_mock import ModbusMockPlc  # noqa: E402
from pmcal.bridge.transfer import push  # noqa: E402
from pmcal.bridge.comptable import CompTable  # noqa: E402
from pmcal.mechanism.ocpm.kinematics import nominal_ik  # noqa: E402
from pmcal.mechanism.ocpm.params import PAPER_TABLE2  # noqa: E402

TARGET_S = {"ads": 0.050, "modbus": 1.0}
PHASES = ("connect_check", "stage", "readback", "commit_ack", "total")


def table(version: int) -> CompTable:
    """A 100x100x2 table from the nominal IK (deg), a little different per version."""
    return CompTable.from_setpoints(
        lambda p, t: np.rad2deg(nominal_ik(np.deg2rad(p), np.deg2rad(t))) + 1e-3 * version,
        machine="ocpm_2dof", version=version, n_phi=100, n_theta=100, motor_limits_deg=(-150.0, 60.0))


def bench(transport: str, repeat: int) -> dict:
    mock = AdsMockPlc(lifetime_s=600.0) if transport == "ads" else ModbusMockPlc(lifetime_s=600.0)
    tables = [table(v) for v in range(1, repeat + 2)]
    with mock:
        link = AdsLink(mock.address) if transport == "ads" else ModbusLink(mock.host, mock.port)
        push(link, tables[0])                                          # warm-up
        runs = []
        for t in tables[1:]:
            rep = push(link, t)
            assert rep.result == "ok" and mock.twin.active_table()[1].tobytes() == t.values.tobytes()
            runs.append(rep.timings_s)
    out = {}
    for phase in PHASES:
        v = np.array([r[phase] for r in runs])
        out[phase] = {"median_ms": 1e3 * float(np.median(v)), "min_ms": 1e3 * float(v.min()),
                      "max_ms": 1e3 * float(v.max())}
    hand_over = np.array([r["stage"] + r["readback"] + r["commit_ack"] for r in runs])
    out["hand_over"] = {"median_ms": 1e3 * float(np.median(hand_over)), "min_ms": 1e3 * float(hand_over.min()),
                        "max_ms": 1e3 * float(hand_over.max())}
    out["repeat"] = repeat
    out["bytes_sent"] = rep.bytes_sent
    out["target_ms"] = 1e3 * TARGET_S[transport]
    out["meets_target"] = bool(out["total"]["median_ms"] <= out["target_ms"])
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeat-ads", type=int, default=20)
    ap.add_argument("--repeat-modbus", type=int, default=5)
    ap.add_argument("--no-loop", action="store_true", help="skip the twin-in-the-loop study")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    set_adslib_log_level(4)
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)

    results = {"ads": bench("ads", args.repeat_ads), "modbus": bench("modbus", args.repeat_modbus)}
    rows = []
    for transport, r in results.items():
        rows.append([transport, r["repeat"], r["bytes_sent"], *(r[p]["median_ms"] for p in PHASES),
                     r["total"]["max_ms"], r["target_ms"], "yes" if r["meets_target"] else "NO"])
    print_table("push of a 100x100x2 LREAL table (ms, median of the runs; total includes connect and check)",
                ["transport", "runs", "bytes", "connect+check", "stage", "read-back", "commit+ack", "total",
                 "total max", "target", "met"], rows)

    if not args.no_loop:
        loop = {}
        for transport, mock in (("ads", AdsMockPlc), ("modbus", ModbusMockPlc)):
            with mock(lifetime_s=600.0) as plc:
                loop[transport] = run_loop(plc, PAPER_TABLE2, n_targets=48, grid=DEFAULT_GRID, seed=1).summary()
        results["twin_in_the_loop"] = loop
        rows = [[t, f"{DEFAULT_GRID[0]}x{DEFAULT_GRID[1]}", s["targets"], s["before"]["rms_deg"],
                 s["before"]["max_deg"], s["after"]["rms_deg"], s["after"]["max_deg"],
                 s["direct_no_table"]["rms_deg"], str(s["plc_equals_table_interpolation"])] for t, s in loop.items()]
        print_table("twin in the loop, paper Table 2 errors: pointing error measured by the virtual tracker (deg)",
                    ["transport", "grid", "poses", "before rms", "before max", "after rms", "after max",
                     "no-table rms", "PLC = table"], rows)
    write_json("bridge_bench", results, args.json)


if __name__ == "__main__":
    main()
