"""Calibration history: a 0.2 mm dent in one link between two campaigns is flagged, nothing else is; two
campaigns of an unchanged machine flag nothing (issue 23).

Per seed: a machine with errors on every limb (0.5 mm / 0.1 deg, normal), three 24-pose campaigns to 60 deg
with tracker noise 0.01 mm: A and B on the machine as it is (a clean pair), C on the machine with one link
0.2 mm shorter (a dent: L1.dl1, L1.dl2, L2.dl1, L2.dl2 in turn), B and C with the same poses and noise.
Each campaign is identified (whole chain) and filed into a history folder; :func:`pmcal.history.compare`
tests A -> B and A -> C at the family-wise rate 0.05.

Target: the dent flagged in every dent pair and nothing else flagged; at most 1 of 20 clean pairs with a
false flag.

Run: python benchmarks/history_bench.py [--seeds 20] [--json PATH] [--example DIR]

``--example DIR`` also files the history of docs/report_history.png into DIR/history: the paper's Table 2
machine calibrated four times, three months apart, L1's first link dented by 0.2 mm before the last
(``pmcal history DIR/history --report history.html``).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import print_table, write_json  # noqa: E402
from pmcal.ocpm.calibration import identify, record_document  # noqa: E402
from pmcal.history import ALPHA, compare, file_calibration, read_record  # noqa: E402
from pmcal.ocpm.io import write_measurements  # noqa: E402
from pmcal.mechanism.ocpm.params import random_errors  # noqa: E402
from pmcal.twin.ocpm.campaign import plan_campaign, run_campaign  # noqa: E402
from pmcal.twin.ocpm.machine import Twin  # noqa: E402
from pmcal.twin.tracker import LaserTracker  # noqa: E402

DENT_MM = -0.2
DENT_LINKS = ("L1.dl1", "L1.dl2", "L2.dl1", "L2.dl2")
POSES, THETA_MAX, SIGMA = 24, 60.0, 0.01


def history_pair(seed: int, folder: Path) -> dict:
    """One seed: flags of the clean pair (A -> B) and of the dent pair (A -> C)."""
    base = random_errors(np.random.default_rng(1000 + seed), 0.5, 0.1)
    link = DENT_LINKS[seed % len(DENT_LINKS)]
    dented = dict(base, **{link: base.get(link, 0.0) + DENT_MM})

    def filed(errors, plan_seed, noise_seed, name):
        meas = run_campaign(Twin(errors), plan_campaign(POSES, THETA_MAX, seed=plan_seed),
                            LaserTracker(SIGMA, np.random.default_rng(noise_seed)))
        write_measurements(folder / f"{name}.csv", meas)
        return read_record(file_calibration(record_document(identify(meas), folder / f"{name}.csv"), folder / name))

    a = filed(base, 3 * seed + 1, 5000 + seed, "a")
    b = filed(base, 3 * seed + 2, 6000 + seed, "b")
    c = filed(dented, 3 * seed + 2, 6000 + seed, "c")
    clean = [x.name for x in compare(a, b, ALPHA) if x.flagged]
    dent = {x.name: x for x in compare(a, c, ALPHA) if x.flagged}
    hit = dent.get(link)
    return {"seed": seed, "dent_link": link, "clean_flags": clean, "dent_flags": sorted(dent),
            "dent_found": hit is not None, "dent_estimate_mm": hit.estimate if hit else None,
            "dent_estimate_std_mm": hit.estimate_std if hit else None,
            "dent_extra_flags": sorted(n for n in dent if n != link)}


def example_history(folder: Path) -> Path:
    """Four calibrations of the paper's Table 2 machine, 91 days apart, a 0.2 mm dent in L1.dl1 before the
    last; returns the history folder."""
    from datetime import datetime, timedelta, timezone

    from pmcal.mechanism.ocpm.params import PAPER_TABLE2

    dented = dict(PAPER_TABLE2, **{"L1.dl1": PAPER_TABLE2.get("L1.dl1", 0.0) + DENT_MM})
    t0 = datetime(2026, 3, 2, 9, 0, tzinfo=timezone.utc)
    for i, errors in enumerate([PAPER_TABLE2] * 3 + [dented]):
        meas = run_campaign(Twin(errors), plan_campaign(POSES, THETA_MAX, seed=i + 1),
                            LaserTracker(SIGMA, np.random.default_rng(50 + i)))
        write_measurements(folder / f"campaign{i + 1}.csv", meas)
        file_calibration(record_document(identify(meas), folder / f"campaign{i + 1}.csv",
                                         date=t0 + timedelta(days=91 * i)), folder / "history")
    return folder / "history"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--json", default=None)
    ap.add_argument("--example", default=None, metavar="DIR", help="also file the example history into DIR")
    args = ap.parse_args(argv)
    if args.example:
        Path(args.example).mkdir(parents=True, exist_ok=True)
        print(f"example history: {example_history(Path(args.example))}")
    rows, results = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(args.seeds):
            folder = Path(tmp) / f"s{seed}"
            folder.mkdir()
            r = history_pair(seed, folder)
            results.append(r)
            rows.append([seed, r["dent_link"], "yes" if r["dent_found"] else "NO",
                         f"{r['dent_estimate_mm']:+.4f} +- {1.96 * r['dent_estimate_std_mm']:.4f}" if r["dent_found"] else "–",
                         ", ".join(r["dent_extra_flags"]) or "–", ", ".join(r["clean_flags"]) or "–"])
            print(f"seed {seed}: dent {r['dent_link']} found {r['dent_found']}, extra {r['dent_extra_flags']}, "
                  f"clean flags {r['clean_flags']}", file=sys.stderr, flush=True)
    print_table("Calibration history: dent of 0.2 mm vs clean pairs (alpha 0.05 family-wise)",
                ["seed", "dent in", "flagged", "attributed mm (95 %)", "other flags (dent pair)", "flags (clean pair)"],
                rows)
    summary = {"seeds": args.seeds, "dents_found": sum(r["dent_found"] for r in results),
               "dent_pairs_with_extra_flags": sum(bool(r["dent_extra_flags"]) for r in results),
               "clean_pairs_with_false_flags": sum(bool(r["clean_flags"]) for r in results),
               "target": "all dents found, no extra flags, <= 1 clean pair in 20 with a false flag"}
    print("\n" + ", ".join(f"{k}: {v}" for k, v in summary.items()))
    write_json("history", {"summary": summary, "per_seed": results, "alpha": ALPHA, "dent_mm": DENT_MM,
                           "poses": POSES, "theta_max_deg": THETA_MAX, "sigma_mm": SIGMA}, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
