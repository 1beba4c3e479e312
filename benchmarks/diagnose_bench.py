"""Discrepancy diagnosis on hidden effects: naming rate, false names, held-out gaps, runtime.

For each case (every effect of the vocabulary at a realistic size, no effect with Gaussian and with
heavy-tailed noise, two effects at once, an effect outside the vocabulary) and each seed: a campaign on
the twin with random geometric errors (limbs 1-2, SS) and the hidden effect(s)
(:func:`pmcal.apps.effect_scenarios.hidden_effect_campaign`: the ``pmcal twin plan --for-diagnosis``
campaign, 128 poses up to 80 deg in random time order, each motor approaching from the side of its last
move, payloads 0/10 kg in blocks of 32 rows, warm-up then cool-down 18 -> 28 -> 18 degC, sigma 0.01 mm,
logged without approach columns), diagnosed without being told (sigma given).

With ``--source xsim`` (or ``both``) the campaigns come from the independent simulator in
``tests/crosssim`` instead (shares no code with pmcal; its own forms of every effect: thermal expansion of
the links only, backlash from the move order, exponential drift creep, eccentricity with random phase),
logged in time order as a CSV without approach columns (warm-up then cool-down 18 -> 28 -> 18 degC,
payloads 0/10 kg in blocks of 32 rows) and read back with :func:`pmcal.io_ocpm.read_measurements`; those
rows are labelled ``xsim``.

Run: python benchmarks/diagnose_bench.py [--seeds 20] [--null-seeds 100] [--poses 128] [--jobs 2]
     [--source twin|xsim|both]
"""

from __future__ import annotations

import argparse
import sys
import time
from multiprocessing import Pool
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import print_table, write_json  # noqa: E402

SIGMA = 0.01
#: case -> (hidden effects, poses (None: --poses), eccentricity amplitude deg (None: realistic),
#: tilt limit of the campaign deg (None: the diagnosis plan's 80))
CASES = {
    "joint_compliance": (["joint_compliance"], None, None, None), "backlash": (["backlash"], None, None, None),
    "encoder_eccentricity": (["encoder_eccentricity"], None, None, None),
    "encoder_eccentricity (70 deg campaign)": (["encoder_eccentricity"], None, None, 70.0),
    "thermal_expansion": (["thermal_expansion"], None, None, None),
    "zero_offset_drift": (["zero_offset_drift"], None, None, None),
    "overconstraint": (["overconstraint"], None, None, None),
    "backlash+thermal_expansion": (["backlash", "thermal_expansion"], None, None, None),
    "none": ([], None, None, None), "none (heavy tails)": ([], None, None, None),
    "outside (joint jitter)": ([], None, None, None),
}


def truth(twin, name: str) -> float:
    """The hidden value in the diagnosis' units (mean over the motors of a per-motor effect)."""
    t = getattr(twin.effects, name)
    return float(np.mean(t)) if isinstance(t, tuple) else float(t)


def within_interval(d, twin, name: str) -> bool:
    """The hidden value lies in the diagnosis' 95 % interval; for overconstraint (24 keys, several
    combinations unidentifiable) the passive-limb keys lie within the fit's covariance (Mahalanobis,
    99.9 %)."""
    from scipy.stats import chi2

    from pmcal.mechanism.ocpm.effects import PASSIVE_KEYS
    from pmcal.mechanism.ocpm.params import is_angular

    if name == "overconstraint":
        idx = [d.final.names.index(k) for k in PASSIVE_KEYS]
        cov = d.final.covariance[np.ix_(idx, idx)] * max(d.final.info["chi2_per_dof"], 1.0)
        true = np.array([np.deg2rad(twin.passive_errors[k]) if is_angular(k) else twin.passive_errors[k]
                         for k in PASSIVE_KEYS])
        diff = d.final.x[idx] - true
        return bool(diff @ np.linalg.solve(cov, diff) < chi2.ppf(0.999, len(idx)))
    v = next(v for v in d.named if v.name == name)
    t = truth(twin, name)
    lo, hi = v.interval
    return bool((lo is None or lo <= t) and (hi is None or t <= hi))


def run_one(job: tuple[str, int, int]) -> dict:
    from pmcal.calib.ocpm.diagnose import DiagnoseOptions, diagnose, limit_blas_threads
    from pmcal.twin.effect_model import EffectChainModel
    from pmcal.apps import effect_scenarios as effects

    limit_blas_threads(1)
    case, seed, n, source = job
    if source == "xsim":
        return run_xsim(case, seed, n)
    names, n_case, ecc, theta_max = CASES[case]
    if ecc is not None:
        effects.REALISTIC["encoder_eccentricity"] = ecc
    meas, twin = effects.hidden_effect_campaign(names, seed, n_case or n, SIGMA, heavy_tails="heavy" in case,
                                                joint_jitter_deg=0.004 if "jitter" in case else 0.0,
                                                theta_max_deg=theta_max or 80.0)
    assert meas.approach is None                  # logged as a user logs it: the approach is inferred
    effects.REALISTIC["encoder_eccentricity"] = 0.01
    t0 = time.perf_counter()
    d = diagnose(meas, EffectChainModel(), DiagnoseOptions(sigma_mm=SIGMA))
    wall = time.perf_counter() - t0
    inside = {v.name: within_interval(d, twin, v.name) for v in d.named if v.name in names}
    return {"case": case, "seed": seed, "poses": len(meas), "named": d.effects, "verdict": d.verdict,
            "gap_before": d.gap_before, "gap_after": d.gap_after, "noise_floor": d.noise_floor, "runtime_s": wall,
            "gap_after_all": d.gap_after_all, "extrapolated": d.extrapolated, "truth_in_interval": inside, "values": {v.name: v.value for v in d.named},
            "intervals": {v.name: v.interval for v in d.named}, "truth": {n: truth(twin, n) for n in names
                                                                          if n != "overconstraint"},
            "unexplained": d.unexplained}


#: cases the independent simulator makes (name -> hidden effects)
XSIM_CASES = {n: [n] for n in ("joint_compliance", "backlash", "encoder_eccentricity", "thermal_expansion",
                               "zero_offset_drift", "overconstraint")} | {"none": []} | {
    "thermal_expansion (steel body)": ["thermal_expansion"], "thermal_expansion (invar links)": ["thermal_expansion"],
    "zero_offset_drift (sine)": ["zero_offset_drift"]}
#: the simulator's other forms of an effect (tests/crosssim/campaign.py FORMS) per case
XSIM_FORMS = {"thermal_expansion (steel body)": {"thermal_expansion": "steel body"},
              "thermal_expansion (invar links)": {"thermal_expansion": "invar links"},
              "zero_offset_drift (sine)": {"zero_offset_drift": "sine"}}


def run_xsim(case: str, seed: int, n: int) -> dict:
    """One diagnosis of a campaign from the independent simulator, written and read back as a CSV."""
    import tempfile

    from pmcal.calib.ocpm.diagnose import DiagnoseOptions, diagnose
    from pmcal.io_ocpm import read_measurements
    from pmcal.twin.effect_model import EffectChainModel
    from tests.crosssim.campaign import hidden_campaign, write_csv

    camp, _, _ = hidden_campaign(XSIM_CASES[case], seed, n, forms=XSIM_FORMS.get(case))
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "xsim.csv"
        write_csv(path, camp)
        meas = read_measurements(path)
    t0 = time.perf_counter()
    d = diagnose(meas, EffectChainModel(), DiagnoseOptions(sigma_mm=SIGMA))
    wall = time.perf_counter() - t0
    return {"case": f"xsim {case}", "seed": seed, "poses": len(meas), "named": d.effects, "verdict": d.verdict,
            "gap_before": d.gap_before, "gap_after": d.gap_after, "noise_floor": d.noise_floor, "runtime_s": wall,
            "gap_after_all": d.gap_after_all, "extrapolated": d.extrapolated, "truth_in_interval": {}, "values": {v.name: v.value for v in d.named},
            "intervals": {v.name: v.interval for v in d.named}, "truth": {}, "unexplained": d.unexplained}


def summarise(rows: list[dict]) -> list[list]:
    table = []
    all_cases = [(c, v[0]) for c, v in CASES.items()] + [(f"xsim {c}", v) for c, v in XSIM_CASES.items()]
    for case, names in all_cases:
        rs = [r for r in rows if r["case"] == case]
        if not rs:
            continue
        right = np.mean([set(names) <= set(r["named"]) for r in rs]) if names else float("nan")
        false = np.mean([bool(set(r["named"]) - set(names)) for r in rs])
        ratio = np.array([r["gap_after"] / r["noise_floor"] for r in rs])
        cover = [v for r in rs for v in r["truth_in_interval"].values()]
        table.append([case, len(rs), right, false, int(sum(bool(set(r["named"]) - set(names)) for r in rs)),
                      float(np.mean([r["unexplained"] for r in rs])),
                      float(np.median([r["gap_before"] for r in rs])), float(np.median([r["gap_after"] for r in rs])),
                      float(np.max(ratio)), float(np.mean(cover)) if cover else float("nan"),
                      float(np.median([r["runtime_s"] for r in rs])), float(np.max([r["runtime_s"] for r in rs]))])
    return table


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20, help="seeds per effect case")
    ap.add_argument("--null-seeds", type=int, default=100, help="seeds of the no-effect cases")
    ap.add_argument("--poses", type=int, default=128)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--cases", default=None, help="comma-separated subset of the cases")
    ap.add_argument("--out", default=None, help="JSON output (default benchmarks/results/diagnose_bench.json)")
    ap.add_argument("--source", choices=("twin", "xsim", "both"), default="twin",
                    help="campaigns from the twin, the independent simulator tests/crosssim, or both")
    args = ap.parse_args(argv)
    jobs = []
    for source in (("twin", "xsim") if args.source == "both" else (args.source,)):
        table = CASES if source == "twin" else XSIM_CASES
        cases = [c for c in args.cases.split(",") if c in table] if args.cases else list(table)
        jobs += [(c, s, args.poses, source) for c in cases
                 for s in range(1000, 1000 + (args.null_seeds if c.startswith("none") else args.seeds))]
    t0 = time.perf_counter()
    with Pool(args.jobs) as pool:
        rows = []
        for i, r in enumerate(pool.imap_unordered(run_one, jobs), 1):
            rows.append(r)
            print(f"\r{i}/{len(jobs)} {r['case']} seed {r['seed']}: {r['named']} "
                  f"{r['gap_before']:.4f} -> {r['gap_after']:.4f} mm ({r['runtime_s']:.1f} s)      ",
                  end="", flush=True)
    print()
    header = ["case", "runs", "named right", "other name", "runs w/ other", "unexplained", "gap before (med)",
              "gap after (med)", "max after/noise", "truth in 95% CI", "runtime med s", "runtime max s"]
    table = summarise(rows)
    print_table(f"Discrepancy diagnosis, {args.poses} poses, sigma {SIGMA} mm", header, table)
    write_json("diagnose_bench", {"poses": args.poses, "sigma_mm": SIGMA, "wall_s": time.perf_counter() - t0,
                                  "header": header, "table": table, "runs": rows}, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
