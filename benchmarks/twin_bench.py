"""Twin speed and accuracy: poses assembled per second, closure residuals, model build times.

Run: python benchmarks/twin_bench.py [--poses N] [--json PATH]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import mujoco
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import print_table, write_json  # noqa: E402
from pmcal.mechanism.ocpm.config import MACHINE_DIR  # noqa: E402
from pmcal.mechanism.ocpm.kinematics import nominal_ik, nominal_pose  # noqa: E402
from pmcal.mechanism.ocpm.params import PAPER_TABLE2, ErrorSet, random_errors  # noqa: E402
from pmcal.twin.ocpm.machine import Twin  # noqa: E402
from pmcal.twin.ocpm.model import ModelIndex, apply_errors, load_model  # noqa: E402


def best_of(fn, repeat=5):
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return min(times), out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--poses", type=int, default=5000)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    n = args.poses
    phi, theta = rng.uniform(0, 2 * np.pi, n), np.deg2rad(rng.uniform(0, 60, n))
    cmd = np.rad2deg(nominal_ik(phi, theta))
    cases = {
        "nominal": {},
        "zero offsets only": {"L1.dtheta": 0.3, "L2.dtheta": -0.2},
        "paper Table 2 (limbs 1-2)": PAPER_TABLE2,
        "0.5 mm / 0.1 deg, every limb + SS": random_errors(rng, 0.5, 0.1),
    }
    rows, results = [], {}
    r0, R0 = nominal_pose(phi, theta)
    for name, params in cases.items():
        twin = Twin(params)
        twin.reach(cmd[:16])                               # warm up the batch
        t, st = best_of(lambda: twin.reach(cmd), repeat=3)
        gaps = st.closure_residual
        entry = {"poses_per_s": n / t, "mean_iterations": float(st.iterations.mean()),
                 "converged": bool(st.converged.all()),
                 "closure_actuated_max_mm": float(gaps[:, :2].max()),
                 "closure_passive_median_mm": float(np.median(gaps[:, 2:])),
                 "closure_passive_max_mm": float(gaps[:, 2:].max())}
        if name == "nominal":
            entry["pose_error_vs_eq7_mm"] = float(np.abs(st.r - r0).max())
        results[name] = entry
        rows.append([name, round(entry["poses_per_s"]), entry["mean_iterations"],
                     entry["closure_actuated_max_mm"], entry["closure_passive_median_mm"],
                     entry["closure_passive_max_mm"]])
    print_table(f"Quasi-static assembly, {n} random poses (theta <= 60 deg), closure stiffness ratio 1000",
                ["machine", "poses/s", "GN iter", "act. gap max mm", "pass. gap median mm", "pass. gap max mm"],
                rows)

    e = ErrorSet.from_dict(random_errors(rng, 0.5, 0.1))
    xml = str(MACHINE_DIR / "ocpm_2dof.xml")
    t_xml, m = best_of(lambda: load_model(), repeat=20)
    index, scratch = ModelIndex.of(m), mujoco.MjData(m)
    t_edit, _ = best_of(lambda: apply_errors(m, e, index=index, data=scratch), repeat=50)
    spec = mujoco.MjSpec.from_file(xml)
    t_compile, _ = best_of(lambda: spec.compile(), repeat=20)
    build = {"xml_load_ms": 1e3 * t_xml, "compiled_edit_setconst_ms": 1e3 * t_edit,
             "mjspec_compile_ms": 1e3 * t_compile}
    print_table("Building a perturbed model", ["step", "ms"],
                [["load MJCF XML", build["xml_load_ms"]],
                 ["insert errors: compiled-model edits + mj_setConst", build["compiled_edit_setconst_ms"]],
                 ["MjSpec compile (alternative path)", build["mjspec_compile_ms"]]])
    target = 5000
    worst = min(r["poses_per_s"] for r in results.values())
    print(f"\ntarget >= {target} poses/s: worst case {worst:.0f} poses/s -> {'met' if worst >= target else 'MISSED'}")
    write_json("twin_bench", {"poses": n, "assembly": results, "model_build": build,
                              "target_poses_per_s": target, "worst_poses_per_s": worst}, args.json)


if __name__ == "__main__":
    main()
