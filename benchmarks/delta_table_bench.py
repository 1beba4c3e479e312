"""The Delta's compensation table: corrections to the controller's nominal IK (nReference 2, the default of
a machine folder) against absolute commands (nReference 0, ``--absolute``), per grid, at held-out targets.

Per seed: ``pmcal --machine <copy of mjcf/delta_3dof> twin measure --poses 48 --seed S`` (random errors on
every frame, tracker noise 0.01 mm), ``identify``; then for each grid over the ``[table]`` box the two
tables of :func:`pmcal.chain.compensation_table`, looked up with :meth:`CompTable.lookup` (bit for bit
the PLC's FB_CompTableLookup: tests/test_comptable_naxes.py) at 200 held-out targets inside the box. The
correction table's command is the nominal IK (the nominal twin's, the controller's) + the looked-up
correction; each command drives the twin with the true errors, and the position error (mm) is reported
with the exact identified IK's ("direct", what the identification leaves) and the nominal IK's.

Run: python benchmarks/delta_table_bench.py [--seeds 3 4 5] [--targets 200] [--json PATH]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import re
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import print_table, write_json  # noqa: E402
from pmcal.chain import compensation_table  # noqa: E402
from pmcal.cli import main as cli  # noqa: E402
from pmcal.io_chain import read_params  # noqa: E402
from pmcal.machines import Machine  # noqa: E402
from pmcal.mjcf import machine_dir  # noqa: E402

GRIDS = ((5, 5, 4), (7, 7, 5), (13, 13, 9), (25, 25, 10))


def campaign(work: Path, seed: int) -> tuple[Machine, dict, dict]:
    """A copy of the Delta's folder, a 48-pose twin campaign with random errors and its identification:
    the machine, the identified parameters and the true errors."""
    folder = work / f"delta_{seed}"
    shutil.copytree(machine_dir("delta_3dof"), folder)
    m = ["-q", "--machine", str(folder)]
    with contextlib.redirect_stdout(io.StringIO()):
        assert cli([*m, "twin", "measure", "--poses", "48", "--seed", str(seed), "-o", str(work / "m.csv")]) == 0
        assert cli([*m, "identify", str(work / "m.csv"), "-o", str(work / "p.json")]) == 0
    machine = Machine.from_folder(folder)
    twin = machine.twin
    params, _ = read_params(work / "p.json", machine.spec, dict(zip(twin.error_keys, twin.error_units())))
    line = next(x for x in (work / "m.csv").read_text().splitlines() if x.startswith("# true errors"))
    truth = {k: float(v) for k, v in re.findall(r"([\w.]+)=([-+0-9.eE]+)", line.split(":", 1)[1])}
    return machine, dict(params), truth


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[3, 4, 5])
    ap.add_argument("--targets", type=int, default=200)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    os.environ.setdefault("MUJOCO_GL", "egl")
    rows, records = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in args.seeds:
            work = Path(tmp) / str(seed)
            work.mkdir()
            machine, params, truth = campaign(work, seed)
            twin = machine.twin
            box = machine.spec.table.box
            lo = np.array([box[a][0] for a in machine.spec.table_axes])
            hi = np.array([box[a][1] for a in machine.spec.table_axes])
            held = lo + (0.05 + 0.9 * np.random.default_rng(seed + 100).random((args.targets, 3))) * (hi - lo)

            def error(commands):
                return np.linalg.norm(twin.forward(commands, truth) - held, axis=1)
            nominal = twin.inverse(held, None)
            e_direct, e_nominal = error(twin.inverse(held, params)), error(nominal)
            for grid in GRIDS:
                corr = compensation_table(machine, params, 1, grid)
                absolute = compensation_table(machine, params, 1, grid, absolute=True)
                e_corr, e_abs = error(nominal + corr.lookup(held)), error(absolute.lookup(held))
                rec = {"seed": seed, "grid": "x".join(map(str, grid)), "values": int(corr.values.size),
                       "correction_max_mm": float(e_corr.max()), "correction_mean_mm": float(e_corr.mean()),
                       "absolute_max_mm": float(e_abs.max()), "absolute_mean_mm": float(e_abs.mean()),
                       "direct_max_mm": float(e_direct.max()), "direct_mean_mm": float(e_direct.mean()),
                       "nominal_max_mm": float(e_nominal.max()),
                       "largest_correction": float(np.abs(corr.values).max())}
                records.append(rec)
                rows.append([seed, rec["grid"], rec["values"], rec["correction_mean_mm"], rec["correction_max_mm"],
                             rec["absolute_mean_mm"], rec["absolute_max_mm"], rec["direct_mean_mm"],
                             rec["direct_max_mm"], rec["nominal_max_mm"]])
    print_table(f"Delta table at {args.targets} held-out targets per seed: position error on the true machine (mm)",
                ["seed", "grid", "values", "corr mean", "corr max", "abs mean", "abs max", "direct mean",
                 "direct max", "nominal max"], rows)
    write_json("delta_table_bench", {"targets": args.targets, "grids": ["x".join(map(str, g)) for g in GRIDS],
                                     "results": records}, args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
