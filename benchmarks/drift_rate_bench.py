"""Per-motor drift on the independent simulator: the campaign-mean rate against the rate at the first pose.

For the cross-sim's drift forms (exponential creep tau = 2 h on one motor or both, a 3-hour oscillation on
both; ``tests/crosssim``), each seed's campaign (128 poses to 80 deg, time order, CSV without approach
columns) is diagnosed as ``benchmarks/diagnose_bench.py`` does, and each motor's reported drift is compared
with the simulator's own: the campaign-mean rate (drift from the first row the diagnosis fits to the last
over that time, ``diagnose_bench.xsim_mean_rates``) against the reported value and its interval, and the family's
rate at the first pose r (``per_motor[].rate_first_pose``, +-1.96 std) against the simulator's initial
rate. z = (reported - truth) / std (statistical std, without the form allowance), signed: times the sign
of the true mean rate (a form's bias has the drift's sign). ``--noise 1e-4`` gives
the near-noise-free fits (the bias of the form); ``--redraw SEED`` keeps one campaign and draws the
tracker noise afresh ``--seeds`` times (does the interval's std hold for that campaign?).

Run: python benchmarks/drift_rate_bench.py [--seeds 20] [--jobs 2] [--noise 0.01] [--redraw SEED]
     [--cases "one motor,creep,sine"] [--out JSON]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from multiprocessing import Pool
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import print_table, write_json  # noqa: E402

SIGMA = 0.01
Z95 = 1.959963984540054
#: case -> the simulator's drift form (tests/crosssim/campaign.py FORMS)
FORMS = {"one motor": "one motor", "creep": None, "sine": "sine"}


def run_one(job: tuple) -> dict:
    """One diagnosis; per motor: truth, reported mean rate, interval, rate at the first pose."""
    from pmcal.calib.ocpm.diagnose import DiagnoseOptions, diagnose, limit_blas_threads
    from pmcal.ocpm.io import read_measurements
    from pmcal.twin.ocpm.effect_model import EffectChainModel
    from benchmarks.diagnose_bench import xsim_mean_rates
    from tests.crosssim.campaign import hidden_campaign, write_csv

    limit_blas_threads(1)
    case, seed, noise, draw = job
    form = FORMS[case]
    camp, _, fx = hidden_campaign(["zero_offset_drift"], seed, forms={"zero_offset_drift": form} if form else None,
                                  sigma_mm=noise if draw is None else 0.0)
    if draw is not None:                                   # the same campaign, fresh tracker noise
        camp.targets = camp.targets + np.random.default_rng([seed, draw]).normal(0.0, noise, camp.targets.shape)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "xsim.csv"
        write_csv(path, camp)
        meas = read_measurements(path)
    d = diagnose(meas, EffectChainModel(), DiagnoseOptions(sigma_mm=SIGMA))
    mean_true = xsim_mean_rates(camp, fx, d)
    out = {"case": case, "seed": seed, "draw": draw, "noise_mm": noise, "named": d.effects, "motors": []}
    v = next((v for v in d.named if v.name == "zero_offset_drift"), None)
    for m in (v.per_motor if v is not None else []):
        i = m["motor"] - 1
        out["motors"].append({"motor": m["motor"], "drifting": bool(fx.drift[i] != 0.0), "carried": m["motor"] in v.motors,
                              "mean_true": float(mean_true[i]), "mean": m["value"], "std": m["std"],
                              "interval": list(m["interval"]), "initial_true": float(fx.drift[i]),
                              "first": m["rate_first_pose"], "first_std": m["rate_first_pose_std"]})
    return out


def summarise(rows: list[dict]) -> list[list]:
    table = []
    for case in FORMS:
        for kind in (True, False):
            ms = [m for r in rows if r["case"] == case for m in r["motors"] if m["drifting"] == kind]
            if not ms:
                continue
            z = np.array([(m["mean"] - m["mean_true"]) / m["std"] for m in ms])
            zs = z * np.sign([m["mean_true"] or 1.0 for m in ms])
            hit = sum(m["interval"][0] <= m["mean_true"] <= m["interval"][1] for m in ms)
            first = sum(abs(m["first"] - m["initial_true"]) <= Z95 * m["first_std"] for m in ms)
            table.append([case, "drifting" if kind else "drift-free", len(ms), f"{hit}/{len(ms)}", f"{first}/{len(ms)}",
                          f"{sum(m['carried'] == kind for m in ms)}/{len(ms)}", float(np.mean(zs)), float(np.std(zs)),
                          float(np.max(np.abs(z))), f"{sum(abs(x) <= Z95 for x in z)}/{len(ms)}"])
    return table


HEADER = ["case", "motor", "checks", "mean rate in interval", "first-pose rate in +-1.96 std", "carried right",
          "z mean (signed)", "z std (signed)", "max |z|", "mean rate in +-1.96 std (no allowance)"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20, help="seeds per case (with --redraw: noise draws)")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--noise", type=float, default=SIGMA, help="tracker noise of the campaigns, mm")
    ap.add_argument("--redraw", type=int, default=None, metavar="SEED",
                    help="one campaign (this seed) with --seeds fresh noise draws")
    ap.add_argument("--cases", default=",".join(FORMS), help="comma-separated subset of " + ", ".join(FORMS))
    ap.add_argument("--out", default=None, help="JSON output (default benchmarks/results/drift_rate_bench.json)")
    ap.add_argument("--summarise", metavar="JSON", default=None, help="print the table of a JSON this script wrote")
    args = ap.parse_args(argv)
    if args.summarise:
        import json

        doc = json.loads(Path(args.summarise).read_text())
        print_table(f"Per-motor drift ({args.summarise}, {len(doc['runs'])} runs)", HEADER, summarise(doc["runs"]))
        return 0
    cases = [c for c in args.cases.split(",") if c in FORMS]
    if args.redraw is not None:
        jobs = [(c, args.redraw, args.noise, k) for c in cases for k in range(args.seeds)]
    else:
        jobs = [(c, s, args.noise, None) for c in cases for s in range(1000, 1000 + args.seeds)]
    with Pool(args.jobs) as pool:
        rows = list(pool.imap_unordered(run_one, jobs) if args.jobs > 1 else map(run_one, jobs))
    table = summarise(rows)
    what = f"seed {args.redraw}, {args.seeds} noise draws" if args.redraw is not None else f"{args.seeds} seeds"
    print_table(f"Per-motor drift, cross-sim, noise {args.noise} mm, {what}", HEADER, table)
    write_json("drift_rate_bench", {"noise_mm": args.noise, "redraw": args.redraw, "header": HEADER, "table": table,
                                    "runs": rows}, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
