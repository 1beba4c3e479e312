"""The folder-machine diagnosis (:mod:`pmcal.calib.chain_diagnose`) on the Delta, on campaigns of an
independent simulator (tests/chain_effects.py: closed-form kinematics, each effect in its own physical
form): how often each case gets exactly its name, how often a clean campaign gets none, how often an
effect shaped unlike every family gets no name (reported unexplained), and whether the per-motor 95 %
intervals cover the truth. 96 poses, 2 minutes apart, temperature +6 K and back, tracker noise 0.01 mm.

Run: python benchmarks/chain_diagnose_bench.py [--seeds 20] [--clean 100] [--json PATH]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import print_table, write_json  # noqa: E402
from pmcal.calib.chain_diagnose import diagnose_chain  # noqa: E402
from pmcal.calib.closed_chain import identify_chain  # noqa: E402
from pmcal.machines import Machine  # noqa: E402
from pmcal.threads import apply_blas_policy  # noqa: E402
from tests.chain_effects import delta_campaign  # noqa: E402

SIGMA = 0.01
#: case -> (simulator effects, the names expected, per-parameter truth to cover)
CASES = {
    "backlash m2": (dict(backlash=(0.0, 0.03, 0.0)), ["backlash"], {"m1.dead_band": 0.0, "m2.dead_band": 0.03,
                                                                      "m3.dead_band": 0.0}),
    "drift m1": (dict(drift=(0.02, 0.0, 0.0)), ["zero_drift"], {"m1.rate": 0.02, "m2.rate": 0.0, "m3.rate": 0.0}),
    "frame drift": (dict(frame=(0.05, -0.03, 0.02, 0.0, 0.0, 0.002)), ["frame_drift"],
                    {"v_x": 0.05, "v_y": -0.03, "v_z": 0.02, "w_z": 0.002}),
    "thermal": (dict(alpha=20e-6), ["thermal_expansion"], {"alpha": 20e-6}),
    "backlash + thermal": (dict(backlash=(0.03, 0.0, 0.03), alpha=15e-6), ["backlash", "thermal_expansion"],
                           {"m1.dead_band": 0.03, "m3.dead_band": 0.03, "alpha": 15e-6}),
    "sag (no family)": (dict(sag=0.05), [], {}),
    "2nd harmonic (no family)": (dict(harmonic=0.01), [], {}),
}


def run(model, seed: int, effects: dict):
    cmd, y, t, temp = delta_campaign(96, np.random.default_rng(seed), sigma=SIGMA, **effects)
    t0 = time.perf_counter()
    base = identify_chain(model, cmd, y, SIGMA)
    dg = diagnose_chain(model, cmd, y, base, time_s=t, temp_c=temp)
    return dg, time.perf_counter() - t0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--clean", type=int, default=100)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    apply_blas_policy()
    model = Machine.builtin("delta_3dof").twin
    rows, out, times = [], {}, []
    cases = dict(CASES, clean=({}, [], {}))
    for name, (effects, expected, truth) in cases.items():
        n = args.clean if name == "clean" else args.seeds
        exact, unexplained, covered, total = 0, 0, 0, 0
        verdicts = []
        for seed in range(n):
            dg, dt = run(model, 100 + seed, effects)
            times.append(dt)
            got = sorted(e.name for e in dg.named)
            exact += got == sorted(expected)
            unexplained += bool(dg.unexplained)
            verdicts.append({"seed": 100 + seed, "named": got, "verdict": dg.verdict,
                             "correlate": dg.unexplained["correlates"][0]["context"] if dg.unexplained else None})
            for e in dg.named:
                for lab, v, s in zip(e.labels, e.values, e.std):
                    if lab in truth:
                        total += 1
                        covered += abs(v - truth[lab]) <= 1.96 * s
        rows.append([name, f"{exact}/{n}", f"{unexplained}/{n}", f"{covered}/{total}" if total else "-"])
        out[name] = {"exact": exact, "n": n, "unexplained": unexplained, "covered": covered, "intervals": total,
                     "runs": verdicts}
        print_table("folder-machine diagnosis on the Delta (independent simulator)",
                    ["case", "exactly its names", "unexplained reported", "95 % intervals cover truth"], rows)
    print(f"median time per diagnosis (identification included): {np.median(times):.1f} s")
    write_json("chain_diagnose_bench", {"cases": out, "median_s": float(np.median(times)), "sigma_mm": SIGMA},
               args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
