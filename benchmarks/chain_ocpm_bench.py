"""The seeded machine ocpm_2dof on the generic closed-chain core vs its dedicated whole-chain path, same data.

Per draw: random errors on every limb and the SS limb (0.5 mm / 0.1 deg, the dedicated benchmark's
sizes, stiffness ratio 1000), a 48-pose campaign of the dedicated twin (theta <= 60 deg, tracker noise
0.01 mm), 24 held-out orientations. Two paths on the same measurements:

- **dedicated**: :func:`pmcal.calib.ocpm.fullchain.identify_full` on the twin's
  :class:`pmcal.twin.ocpm.forward.FullChainModel` (its own error vocabulary and sensitivities), compensation by
  :func:`pmcal.calib.ocpm.fullchain.chain_commands_deg`;
- **generic**: :func:`pmcal.calib.closed_chain.identify_chain` on
  :class:`pmcal.twin.closed_chain.ClosedChainTwin` of ``mjcf/ocpm_2dof/chain`` (the same MJCF described as
  data: frame errors, base set by pivoted QR, compliant closures), compensation by
  :func:`pmcal.calib.closed_chain.compensate_targets` (inverse kinematics on phi, theta).

Judged by the true pointing error of the dedicated twin (true errors) driven to each path's commands at
the held-out orientations (mean over poses and draws). Targets (issue 22): generic <= 1.1x the
dedicated error, generic time (identification + compensation) <= 3x the dedicated time.

Run: python benchmarks/chain_ocpm_bench.py [--draws 5] [--json PATH]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import print_table, write_json  # noqa: E402
from pmcal.calib.closed_chain import compensate_targets, identify_chain  # noqa: E402
from pmcal.calib.ocpm.fullchain import FullChainOptions, chain_commands_deg, identify_full  # noqa: E402
from pmcal.mechanism.ocpm.params import errors_and_ratio, random_errors  # noqa: E402
from pmcal.mechanism.rotations import pointing_error, tilt_torsion  # noqa: E402
from pmcal.mjcf import machine_dir  # noqa: E402
from pmcal.threads import apply_blas_policy  # noqa: E402
from pmcal.twin.ocpm.campaign import plan_campaign, run_campaign  # noqa: E402
from pmcal.twin.closed_chain import ClosedChainTwin  # noqa: E402
from pmcal.twin.ocpm.forward import FullChainModel  # noqa: E402
from pmcal.twin.ocpm.machine import Twin  # noqa: E402
from pmcal.twin.tracker import LaserTracker  # noqa: E402

SIGMA = 0.01
ACCURACY_MAX, TIME_MAX = 1.1, 3.0


def pointing_deg(twin: Twin, cmd: np.ndarray, phi: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """True pointing error (deg) per pose of the twin driven to ``cmd``; NaN where a command is missing."""
    out = np.full(len(cmd), np.nan)
    ok = np.isfinite(cmd).all(axis=1)
    st = twin.reach(cmd[ok])
    out[ok] = np.rad2deg(pointing_error(st.R, tilt_torsion(np.deg2rad(phi[ok]), np.deg2rad(theta[ok]))))
    return out


def one_draw(d: int, dedicated: FullChainModel, generic: ClosedChainTwin) -> dict:
    rng = np.random.default_rng(1000 + d)
    errors = random_errors(rng, 0.5, 0.1)
    twin = Twin(errors)
    meas = run_campaign(twin, plan_campaign(48, 60, seed=d), LaserTracker(SIGMA, np.random.default_rng(d)))
    test = plan_campaign(24, 60, seed=500 + d)
    task = np.stack([test.phi_deg, test.theta_deg], axis=1)

    t0 = time.perf_counter()
    res = identify_full(meas, dedicated, FullChainOptions())
    e, _ = errors_and_ratio(res.names, res.x)
    t1 = time.perf_counter()
    cmd_d = chain_commands_deg(dedicated, e, test.phi_deg, test.theta_deg, stiffness_ratio=res.info["stiffness_ratio"])
    t2 = time.perf_counter()
    gres = identify_chain(generic, meas.m_cmd_deg, meas.targets, SIGMA)
    t3 = time.perf_counter()
    cmd_g = compensate_targets(generic, gres.params, task)
    t4 = time.perf_counter()
    err_d = pointing_deg(twin, cmd_d, test.phi_deg, test.theta_deg)
    err_g = pointing_deg(twin, cmd_g, test.phi_deg, test.theta_deg)
    return {"draw": d, "dedicated_deg": float(np.nanmean(err_d)), "generic_deg": float(np.nanmean(err_g)),
            "dedicated_missing": int(np.isnan(err_d).sum()), "generic_missing": int(np.isnan(err_g).sum()),
            "dedicated_identify_s": t1 - t0, "dedicated_compensate_s": t2 - t1,
            "generic_identify_s": t3 - t2, "generic_compensate_s": t4 - t3,
            "generic_rank": gres.rank, "generic_keys": len(gres.basis.keys), "generic_chi2_per_dof": gres.chi2_per_dof,
            "dedicated_chi2_per_dof": float(res.info["chi2_per_dof"])}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--draws", type=int, default=5, help="random error sets (default 5)")
    ap.add_argument("--json", default=None, help="output (default benchmarks/results/chain_ocpm_bench.json)")
    args = ap.parse_args(argv)
    apply_blas_policy()
    dedicated = FullChainModel()
    generic = ClosedChainTwin.from_folder(machine_dir("ocpm_2dof") / "chain")
    runs = []
    for d in range(args.draws):
        r = one_draw(d, dedicated, generic)
        runs.append(r)
        print(f"  draw {d}: dedicated {r['dedicated_deg']:.5f} deg ({r['dedicated_identify_s']:.1f} + "
              f"{r['dedicated_compensate_s']:.1f} s), generic {r['generic_deg']:.5f} deg "
              f"({r['generic_identify_s']:.1f} + {r['generic_compensate_s']:.1f} s, rank {r['generic_rank']}/"
              f"{r['generic_keys']}, chi2/dof {r['generic_chi2_per_dof']:.2f})", flush=True)
    ded = float(np.mean([r["dedicated_deg"] for r in runs]))
    gen = float(np.mean([r["generic_deg"] for r in runs]))
    t_d = float(np.mean([r["dedicated_identify_s"] + r["dedicated_compensate_s"] for r in runs]))
    t_g = float(np.mean([r["generic_identify_s"] + r["generic_compensate_s"] for r in runs]))
    summary = {"dedicated_deg": ded, "generic_deg": gen, "accuracy_ratio": gen / ded, "dedicated_s": t_d,
               "generic_s": t_g, "time_ratio": t_g / t_d,
               "missing": {"dedicated": sum(r["dedicated_missing"] for r in runs),
                           "generic": sum(r["generic_missing"] for r in runs)}}
    summary["pass"] = bool(summary["accuracy_ratio"] <= ACCURACY_MAX and summary["time_ratio"] <= TIME_MAX)
    print_table(f"ocpm_2dof: generic closed-chain core vs dedicated whole chain ({args.draws} draws, 48 poses, "
                f"24 held-out; targets <= {ACCURACY_MAX}x error, <= {TIME_MAX}x time)",
                ["path", "pointing error deg", "identify + compensate s", "ratio err", "ratio time"],
                [["dedicated", ded, t_d, 1.0, 1.0], ["generic", gen, t_g, gen / ded, t_g / t_d]])
    write_json("chain_ocpm_bench", {"targets": {"accuracy": ACCURACY_MAX, "time": TIME_MAX}, "summary": summary,
                                    "runs": runs}, args.json)
    return 0 if summary["pass"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
