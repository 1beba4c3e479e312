"""Planar 2-DOF robot (paper 003): reproduction of the paper's simulation (Tables 3-6, Fig. 8) over many noise
realisations on the MuJoCo twin, the noise floor of the paper's positions, and the calibration-region
trade-off of this project's noise-optimal positions. Prints tables; writes benchmarks/results/planar_bench.json.

Settings per group 1-6 (paper Table 2): ``seed`` = the paper's method (K = 6 on W, TSVD, eq. 30 loop) under
the noise of eq. 34-35; ``paper_scale_only`` = the same with the servo error off; ``ours`` = noise-optimal
positions in the configured calibration region + GLS, noise of eq. 34-35.

Run: python benchmarks/planar_bench.py [--runs 500] [--quick]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import print_table, write_json  # noqa: E402
from pmcal.mechanism.planar.region import Region  # noqa: E402
from pmcal.calib.planar.design import (boundary_positions, condition_study, optimal_positions,  # noqa: E402
                                 zero_offset_covariance)
from pmcal.calib.planar.identification import identify  # noqa: E402
from pmcal.mechanism.planar.kinematics import inverse  # noqa: E402
from pmcal.twin.planar.config import default_machine  # noqa: E402
from pmcal.apps.planar.study import GROUPS, PAPER, evaluate_at, run_study, settings  # noqa: E402
from pmcal.twin.planar.twin import PlanarTwin  # noqa: E402


def reproduction(machine, runs: int, seed: int) -> dict:
    g, ws, cal = machine.geometry, machine.workspace, machine.calibration
    paper_pos = boundary_positions(ws, cal.n_per_boundary)
    ours_pos = optimal_positions(g, machine.design.region, machine.design.positions, machine.noise,
                                 step=machine.design.grid_step)
    out = {"positions": {"seed": paper_pos.tolist(), "ours": ours_pos.tolist()}, "groups": {}}
    rows3, rows45 = [], []
    for gi, grp in enumerate(GROUPS):
        err = machine.preset(grp)
        twin = PlanarTwin(err, machine)
        out["groups"][grp] = {}
        before = float(evaluate_at(twin, paper_pos, np.zeros((1, 2)))[0])
        for si, s in enumerate(settings(machine, paper_pos, ours_pos)):
            t0 = time.perf_counter()
            res = run_study(err, s.positions, s.noise, runs, seed=seed + 100 * gi + si, method=s.method,
                            mu0=cal.mu0, max_iter=cal.max_iterations, twin=twin)
            dt = time.perf_counter() - t0
            d = res.summary()
            d["dpmax_paper_positions_before_mm"] = before
            d["dpmax_paper_positions_after_median_mm"] = float(np.median(evaluate_at(twin, paper_pos, res.comp_deg)))
            d["wall_s"] = dt
            out["groups"][grp][s.name] = d
            s3 = PAPER["table3"][grp]
            rows3.append([grp, s.name, f"{s3[1]:.3f}/{s3[3]:.3f}",
                          "{:.4f}/{:.4f}".format(*d["delta_deg_median"]), "{:.4f}/{:.4f}".format(*d["delta_deg_rms"]),
                          f"{s3[4]:.3f}", f"{d['dp0_before_mm']:.3f}", f"{s3[5]:.3f}", f"{d['dp0_after_median_mm']:.3f}",
                          f"{d['converged_fraction']:.2f}", f"{d['m_median']:.0f}"])
            rows45.append([grp, s.name, f"{PAPER['table4'][grp][0]:.3f}/{PAPER['table4'][grp][1]:.3f}",
                           f"{before:.3f}/{d['dpmax_paper_positions_after_median_mm']:.3f}",
                           "{:.3f}/{:.3f}".format(*PAPER["table5"][grp]), "{:.3f}/{:.3f}".format(*d["delta_M_median_mm"]),
                           f"{PAPER['table6'][grp]:.2f}", "" if d["cond_later_mean"] is None else f"{d['cond_later_mean']:.2f}"])
    print_table(f"Table 3 (seed) vs twin, {runs} runs per group and setting: δ = |compensation - set| (deg), "
                "Δp0 (mm)", ["group", "setting", "δ1/δ2 seed", "δ median", "δ RMS", "Δp0 bef. seed", "Δp0 bef.",
                             "Δp0 aft. seed", "Δp0 aft. median", "converged", "m median"], rows3)
    print_table("Tables 4-6: Δp_max at the paper positions before/after (mm), δM (mm), mean κ",
                ["group", "setting", "Δpmax seed", "Δpmax ours (median)", "δMx/δMy seed", "δMx/δMy median",
                 "κ seed", "κ mean"], rows45)
    return out


def condition(machine) -> dict:
    ns = np.arange(3, 22, 2)
    k1, km = condition_study(machine.geometry, machine.workspace, ns, machine.preset("group1").drM)
    print_table("Fig. 8: condition numbers (seed at n = 3: κ1 = 475.34, κm = 472.54)", ["n", "κ1", "κm"],
                [[int(n), float(a), float(b)] for n, a, b in zip(ns, k1, km)])
    return {"n": ns.tolist(), "kappa1": k1.tolist(), "kappam": km.tolist(), "seed": PAPER["fig8"]}


def region_sweep(machine, quick: bool) -> list[dict]:
    """Cramér-Rao bound of the zero offsets (GLS) for noise-optimal positions in W enlarged by a margin."""
    g, ws, noise = machine.geometry, machine.workspace, machine.noise
    seed_sd = np.rad2deg(np.sqrt(np.diag(zero_offset_covariance(g, boundary_positions(ws, 3), noise))[:2]))
    rows, out = [["paper positions", 6, "{:.4f}/{:.4f}".format(*seed_sd), ""]], []
    margins = (0, 100, 200, 300) if quick else (0, 50, 100, 150, 200, 250, 300)
    for K in (6, 10):
        for m in margins:
            region = Region(x=(-ws.b / 2 - m, ws.b / 2 + m), y=(ws.y_lower - m, ws.y_upper + m),
                            min_transmission=machine.design.region.min_transmission,
                            min_platform=machine.design.region.min_platform, scale_range=machine.scale_range)
            r = optimal_positions(g, region, K, noise, step=20.0 if m >= 100 else 10.0, restarts=6)
            sd = np.rad2deg(np.sqrt(np.diag(zero_offset_covariance(g, r, noise))[:2]))
            out.append({"K": K, "margin_mm": m, "crlb_deg": sd.tolist(), "positions": r.tolist()})
            rows.append([f"W + {m} mm", K, "{:.4f}/{:.4f}".format(*sd),
                         f"x {r[:, 0].min():.0f}..{r[:, 0].max():.0f}, y {r[:, 1].min():.0f}..{r[:, 1].max():.0f}"])
    print_table("Zero-offset standard deviation (Cramér-Rao, GLS, noise eq. 34-35) vs calibration region",
                ["region", "K", "σ(Δθ1)/σ(Δθ2) deg", "positions span (mm)"], rows)
    return out


def speed(machine) -> dict:
    twin = PlanarTwin(machine.preset("group1"), machine)
    rng = np.random.default_rng(0)
    r = np.stack([rng.uniform(-240, 240, 600), rng.uniform(-782, -632, 600)], 1)
    motor = inverse(machine.geometry, r)
    twin.assemble(motor[:6])
    out = {}
    for n in (6, 600):
        t0 = time.perf_counter()
        reps = 20 if n == 6 else 3
        for _ in range(reps):
            twin.assemble(motor[:n])
        out[f"assemble_{n}_poses_ms"] = (time.perf_counter() - t0) / reps * 1e3
    y = np.zeros(5)
    t0 = time.perf_counter()
    for _ in range(200):
        identify(machine.geometry, r[:6], y, noise=machine.noise)
    out["identify_ms"] = (time.perf_counter() - t0) / 200 * 1e3
    print_table("Speed", ["what", "ms"], [[k, v] for k, v in out.items()])
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=500, help="noise realisations per group and setting")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--quick", action="store_true", help="100 runs, fewer region margins")
    ap.add_argument("-o", "--output", default=None, help="JSON path (default benchmarks/results/planar_bench.json)")
    a = ap.parse_args()
    runs = 100 if a.quick else a.runs
    machine = default_machine()
    t0 = time.perf_counter()
    data = {"runs": runs, "noise": {"scale_sigma_mm": machine.noise.scale,
                                    "servo_sigma_deg": float(np.rad2deg(machine.noise.servo))},
            "condition": condition(machine), "reproduction": reproduction(machine, runs, a.seed),
            "region_sweep": region_sweep(machine, a.quick), "speed": speed(machine), "paper_tables": PAPER}
    data["wall_s"] = time.perf_counter() - t0
    write_json("planar_bench", data, a.output)


if __name__ == "__main__":
    main()
