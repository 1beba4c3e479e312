"""A strained planar loop: identification with the assembly's exact derivative against the Gauss-Newton one.

tests/corpus/nopour_3rrr (a planar 3-RRR whose platform closes to two chains by 3-D site connects: its
out-of-plane errors strain the loops, which keep a gap) at its machine.toml's error sizes and at larger ones
(0.5 and 1 deg tilts, 0.3 and 0.5 mm offsets: a hand-built or 3-D printed machine). Per seed, the demo's pipeline
(:func:`pmcal.studies.chain_demo.chain_demo`: D-optimal 48-pose plan, campaign on the twin with random errors
of the sizes, identify, 60 held-out targets compensated and driven on the true machine) twice: with the
twin's derivative as it is (the gap's second-order terms, ``ClosedChainTwin._strain_terms``) and with the
Gauss-Newton part alone (those terms switched off, the derivative before they were added).

Figures per variant: chi2/dof of the fit, the compensated position error RMS (mm) on the held-out targets and
its ratio to the predicted one, median and worst over the seeds; the runs whose chi2/dof is above 2 (a fit
that did not reach the data) are counted.

Run: python benchmarks/strained_loop_bench.py [--seeds 10] [--json PATH]
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import print_table, write_json  # noqa: E402

MODEL = Path(__file__).resolve().parent.parent / "tests" / "corpus" / "nopour_3rrr"
#: error sizes studied: label -> replacements in the machine.toml
SIZES = {"machine.toml (0.1 deg, 0.1 mm)": {},
         "0.5 deg, 0.3 mm": {"angle_deg = 0.1": "angle_deg = 0.5", "position_mm = 0.1": "position_mm = 0.3"},
         "1.0 deg, 0.5 mm": {"angle_deg = 0.1": "angle_deg = 1.0", "position_mm = 0.1": "position_mm = 0.5"}}


def machine_with(sizes: dict[str, str], folder: Path):
    """The 3-RRR with its [errors] lines replaced (a copy in ``folder``)."""
    from pmcal.machines import Machine

    shutil.copytree(MODEL, folder)
    toml = folder / "machine.toml"
    text = toml.read_text()
    for old, new in sizes.items():
        text = text.replace(old, new)
    toml.write_text(text)
    return Machine.from_folder(folder)


def run(machine, seed: int, exact: bool) -> dict:
    from pmcal.studies.chain_demo import chain_demo
    from pmcal.twin.closed_chain import ClosedChainTwin

    saved = ClosedChainTwin._strain_terms
    if not exact:
        ClosedChainTwin._strain_terms = lambda *a: None
    try:
        s = chain_demo(machine, seed).summary()
    finally:
        ClosedChainTwin._strain_terms = saved
    return {"seed": seed, "exact": exact, "chi2_per_dof": s["chi2_per_dof"], "after_mm": s["position_rms_after_mm"],
            "predicted_mm": s["position_rms_predicted_mm"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    rows, table = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for i, (label, sizes) in enumerate(SIZES.items()):
            machine = machine_with(sizes, Path(tmp) / f"m{i}")
            for exact in (True, False):
                got = []
                for seed in range(1, args.seeds + 1):
                    r = run(machine, seed, exact) | {"sizes": label}
                    got.append(r)
                    print(f"\r{label}, {'exact' if exact else 'Gauss-Newton'} derivative, seed {seed}: chi2/dof "
                          f"{r['chi2_per_dof']:.2f}, after {r['after_mm']:.4f} mm      ", end="", flush=True)
                rows += got
                after = np.array([r["after_mm"] for r in got])
                ratio = after / np.array([r["predicted_mm"] for r in got])
                chi2 = np.array([r["chi2_per_dof"] for r in got])
                table.append([label, "exact" if exact else "Gauss-Newton", len(got), float(np.median(chi2)),
                              int(np.sum(chi2 > 2.0)), float(np.median(after)), float(after.max()),
                              float(np.median(ratio)), float(ratio.max())])
    print()
    header = ["errors", "derivative", "seeds", "chi2/dof median", "chi2/dof > 2", "after mm median", "after mm worst",
              "after/predicted median", "after/predicted worst"]
    print_table("nopour_3rrr, demo pipeline (48 planned poses, 60 held-out targets)", header, table)
    write_json("strained_loop_bench", {"header": header, "table": table, "runs": rows}, args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
