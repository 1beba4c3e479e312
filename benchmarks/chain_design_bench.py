"""Planned (D-optimal) vs random campaigns of the data-only machines: what ``pmcal --machine DIR twin plan``
buys, measured on identification, not on its own prediction.

Per machine, campaign size and seed: random geometric errors of the machine.toml's sizes
(:func:`pmcal.chain.random_errors`); two campaigns of the same size on the twin, tracker noise of the TOML:
the plan (:func:`pmcal.chain.plan`, D-optimal from a pool drawn over the workspace) and the poses
``twin measure`` draws at random; each identified (:func:`pmcal.chain.identify`). Judged on 60 held-out
poses: RMS distance between the nests the identified model predicts and the true machine's (mm). Also the
plan's own prediction (``CampaignDesign.gain``: geometric-mean ratio of posterior standard deviations).

Run: python benchmarks/chain_design_bench.py [--seeds 10] [--poses 24 48] [--machines delta_3dof hexapod_6dof]
     [--json PATH]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import print_table, write_json  # noqa: E402
from pmcal.chain import campaign, identify, plan, random_errors  # noqa: E402
from pmcal.machines import Machine  # noqa: E402
from pmcal.threads import apply_blas_policy  # noqa: E402


def held_out_rms(machine, params: dict, truth: dict, commands: np.ndarray) -> float:
    """RMS distance (mm) between the nests of the identified and of the true machine at ``commands``."""
    twin = machine.twin
    d = np.linalg.norm(twin.targets(commands, params) - twin.targets(commands, truth), axis=2)
    return float(np.sqrt(np.nanmean(d ** 2)))


def one(machine, poses: int, seed: int) -> dict:
    rng = np.random.default_rng(5000 + seed)
    truth = random_errors(machine, rng)
    held = machine.twin.sample_commands(60, rng)
    design = plan(machine, poses, seed=seed)
    planned, _ = campaign(machine, poses, seed=seed, errors=truth, commands=design.commands)
    drawn, _ = campaign(machine, poses, seed=seed, errors=truth)
    rms = {name: held_out_rms(machine, identify(machine, meas).params, truth, held)
           for name, meas in (("planned", planned), ("random", drawn))}
    return {"seed": seed, "predicted_gain": design.gain, **rms}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--poses", type=int, nargs="+", default=[24, 48])
    ap.add_argument("--machines", nargs="+", default=["delta_3dof", "hexapod_6dof"])
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    apply_blas_policy()
    rows, out = [], {}
    for name in args.machines:
        machine = Machine.builtin(name)
        for poses in args.poses:
            runs = [one(machine, poses, s) for s in range(args.seeds)]
            planned = np.array([r["planned"] for r in runs])
            drawn = np.array([r["random"] for r in runs])
            wins = int(np.sum(planned < drawn))
            realized = float(np.exp(np.mean(np.log(drawn / planned))))
            predicted = float(np.exp(np.mean(np.log([r["predicted_gain"] for r in runs]))))
            rows.append([name, poses, f"{np.median(planned):.4f}", f"{np.median(drawn):.4f}",
                         f"{realized:.2f}", f"{predicted:.2f}", f"{wins}/{len(runs)}"])
            out[f"{name}/{poses}"] = {"runs": runs, "realized_gain": realized, "predicted_gain": predicted,
                                      "planned_better": wins}
            print_table("planned vs random campaigns (held-out nest prediction error, mm)",
                        ["machine", "poses", "planned median", "random median", "gain (realized)",
                         "gain (predicted)", "planned better"], rows)
    write_json("chain_design", {"seeds": args.seeds, "cases": out}, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
