"""Regenerate tests/data/fullchain_setpoints_6ec3c9e_tight.csv: the whole-chain compensation commands of
the saved reference's targets, computed by pmcal at commit 6ec3c9e (per-target Newton on the assembled
forward model, an independent solver from today's bordered Newton) but converged to a pointing residual
below 1e-11 deg instead of the 1e-7 deg it was saved with.

Run from the repository root: python tools/tight_reference.py  (needs git; takes ~1 min)
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
REF = ROOT / "tests" / "data" / "fullchain_setpoints_6ec3c9e.csv"
OUT = ROOT / "tests" / "data" / "fullchain_setpoints_6ec3c9e_tight.csv"
COMMIT = "6ec3c9e"
TOL_DEG = 1e-11

CHILD = r'''
import sys
import numpy as np
from pmcal.calib.ocpm.fullchain import setpoints
from pmcal.mechanism.ocpm.params import ErrorSet, random_errors
from pmcal.mechanism.ocpm.config import default_geometry
from pmcal.twin.ocpm.forward import FullChainModel
lines = [l for l in open(sys.argv[1]).read().splitlines() if not l.startswith("#")]
d = np.genfromtxt(lines, delimiter=",", names=True)
geom = default_geometry()
e = ErrorSet.from_dict(random_errors(np.random.default_rng(7), 0.5, 0.1), geom.n_limbs, geom.actuated)
for ratio in (1000.0, 100.0):
    s = d[d["stiffness_ratio"] == ratio]
    for p, t in zip(s["phi_deg"], s["theta_deg"]):       # one by one: unreachable targets stay NaN
        try:
            m = setpoints(FullChainModel(geom, ratio), e, [p], [t], ratio, tol_deg=float(sys.argv[2]), max_iter=40)[0]
        except ValueError:
            m = (np.nan, np.nan)
        print(",".join(repr(float(v)) for v in (ratio, p, t, m[0], m[1])))
'''


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        src, pkg = Path(tmp) / "src", Path(tmp) / "pkg"
        src.mkdir()
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", COMMIT], check=True, capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(src)], input=archive, check=True)
        (pkg / "pmcal").parent.mkdir()
        (pkg / "pmcal").symlink_to(src / "pmcal", target_is_directory=True)
        for sub in ("mechanism", "twin", "calib", "bridge", "mjcf", "plc"):
            (src / "pmcal" / sub).symlink_to(src / sub, target_is_directory=True)
        env = dict(os.environ, PYTHONPATH=str(pkg))
        rows = subprocess.run([sys.executable, "-c", CHILD, str(REF), str(TOL_DEG)], check=True, text=True,
                              capture_output=True, env=env, cwd=tmp).stdout
    params = [line for line in REF.read_text().splitlines() if line.startswith("# params:")]
    OUT.write_text(
        f"# Whole-chain compensation commands (deg) computed by pmcal at commit {COMMIT} (per-target Newton from\n"
        f"# the nominal IK, tol {TOL_DEG:g} deg) for random_errors(default_rng(7), 0.5, 0.1); nan: out of reach.\n"
        "# Same targets as fullchain_setpoints_6ec3c9e.csv (saved with tol 1e-7 deg); made by tools/tight_reference.py\n"
        + "\n".join(params) + "\nstiffness_ratio,phi_deg,theta_deg,m1_deg,m2_deg\n" + rows)


if __name__ == "__main__":
    main()
