"""Calibration history of a machine folder (``pmcal --machine DIR identify ... --history H``, ``pmcal history H``)
on a copy of the Delta: records in the machine's structural base set (the same parameters and combinations for
every campaign, whatever its poses), the change between two campaigns of one machine consistent with the filed
covariances, a moved error found in the combinations that hold it, a campaign too poor to compare not filed.

The truth is the twin's error set, written here; the expected change of each combination comes from the base
set's own regrouping (``BaseSet.combination_values``), the chi-square bound from the number of combinations.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from pmcal.chain import reference_basis
from pmcal.cli import main
from pmcal.history import compare, read_history
from pmcal.machines import resolve
from pmcal.mjcf import machine_dir

MOVED, DENT_MM = "arm1.dz", 0.3


def _run(*argv) -> int:
    return main(["--quiet", *map(str, argv)])


@pytest.fixture(scope="module")
def filed(tmp_path_factory):
    """Two campaigns of one Delta and one after ``arm1.dz`` moved by 0.3 mm, each filed into H."""
    tmp = tmp_path_factory.mktemp("chain_history")
    folder = tmp / "my_delta"
    shutil.copytree(machine_dir("delta_3dof"), folder)
    twin = resolve(str(folder)).twin
    rng = np.random.default_rng(11)
    errors = {k: float(rng.normal(0.0, s)) for k, s in zip(twin.error_keys, twin.prior_std())}
    units = dict(zip(twin.error_keys, twin.error_units()))
    moved = dict(errors, **{MOVED: errors[MOVED] + DENT_MM})
    for name, errs in (("A", errors), ("B", moved)):
        (tmp / f"{name}.json").write_text(json.dumps({"mechanism": "delta_3dof", "params": errs, "units": units}))
    for i, (name, seed) in enumerate((("A", 4), ("A", 5), ("B", 6))):
        assert _run("--machine", folder, "twin", "measure", "--poses", 48, "--seed", seed, "--errors",
                    tmp / f"{name}.json", "-o", tmp / f"m{i}.csv") == 0
        assert _run("--machine", folder, "identify", tmp / f"m{i}.csv", "-o", tmp / f"p{i}.json",
                    "--history", tmp / "H") == 0
    return folder, tmp


def test_records_share_the_structural_base_set(filed):
    folder, tmp = filed
    records = read_history(tmp / "H")
    assert len(records) == 3
    basis = reference_basis(resolve(str(folder)))
    for r in records:
        assert r.names == basis.base
        assert [r.doc["params"][n]["estimates"] for n in r.names] == [basis.combinations[n] for n in basis.base]
        assert r.model == "closed_chain" and r.machine == "delta_3dof"
    # each parameters file of identify --history is in that base set too
    assert json.loads((tmp / "p0.json").read_text())["identifiable"] == basis.base


def test_same_machine_twice_is_consistent_and_quiet(filed):
    _, tmp = filed
    a, b, _ = read_history(tmp / "H")
    d = b.value - a.value
    chi2 = float(d @ np.linalg.solve(a.cov + b.cov, d))
    n = len(d)
    assert n - 4 * np.sqrt(2 * n) < chi2 < n + 4 * np.sqrt(2 * n), chi2
    assert not [c.name for c in compare(a, b) if c.flagged]


def test_a_moved_error_shows_in_its_combinations(filed, capsys):
    folder, tmp = filed
    _, b, c = read_history(tmp / "H")
    basis = reference_basis(resolve(str(folder)))
    expected = dict(zip(basis.base, basis.combination_values({MOVED: DENT_MM})))
    holds = {n for n, v in expected.items() if abs(v) > 0.05}
    assert holds                                                   # the dent is visible in the base set
    changes = {ch.name: ch for ch in compare(b, c)}
    flagged = {n for n, ch in changes.items() if ch.flagged}
    assert holds <= flagged, (holds, flagged)
    for n in holds:                                                # within the noise + 2nd order (0.01 mm)
        assert abs(changes[n].estimate - expected[n]) < 4 * changes[n].estimate_std + 0.01, n
    # other flags are the dent's second-order effects on the other combinations (the regrouping of each
    # is exact at the nominal machine only): a few, each consistent with no move (noise + 2nd order), far
    # below the dent
    assert all(abs(changes[n].estimate) < 4 * changes[n].estimate_std + 0.01 for n in flagged - holds), \
        {n: (changes[n].estimate, changes[n].estimate_std) for n in flagged - holds}
    capsys.readouterr()
    assert main(["history", str(tmp / "H")]) == 0
    moved = [line for line in capsys.readouterr().out.splitlines() if line.startswith("moved:")]
    assert len(moved) == 1 and all(n in moved[0] for n in holds), moved


def test_a_poor_campaign_is_not_filed(filed, capsys):
    folder, tmp = filed
    assert _run("--machine", folder, "twin", "measure", "--poses", 4, "--seed", 9, "--errors", tmp / "A.json",
                "-o", tmp / "few.csv") == 0
    capsys.readouterr()
    assert main(["--machine", str(folder), "identify", str(tmp / "few.csv"), "-o", str(tmp / "few.json"),
                 "--history", str(tmp / "H")]) == 0
    assert "not filed" in capsys.readouterr().err
    assert len(read_history(tmp / "H")) == 3
