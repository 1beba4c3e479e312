"""Figures in the task's own units (issue 34): an orientation machine's demo headline, summary and report
are in degrees; a mixed task (Reachy Mini's head: x, y, z, rx, ry, rz) gets both mm and deg.

The figures are checked against the per-coordinate RMS the summary also reports (the RMS of the norm over a
family's coordinates is the root of the sum of their squared RMS), and the orientation machine's headline
against the predicted error in the same unit (within 3x: the covariance's prediction of a 60-target RMS)."""

import json
import math
import re
from pathlib import Path

import pytest

from pmcal.cli import main
from pmcal.mjcf import machine_dir

CORPUS = Path(__file__).parent / "corpus"


def _demo(folder, out, capsys):
    assert main(["--machine", str(folder), "demo", "--out", str(out)]) == 0
    line = capsys.readouterr().out.strip().splitlines()[0]
    return line, json.loads((out / "summary.json").read_text())


def test_orientation_machine_headline_is_in_degrees(tmp_path, capsys):
    line, s = _demo(machine_dir("ocpm_2dof") / "chain", tmp_path / "d", capsys)
    m = re.search(r"orientation error on \d+ held-out targets ([\d.]+) -> ([\d.]+) deg RMS \(predicted ([\d.]+)\)",
                  line)
    assert m and " mm" not in line and "nan" not in line, line
    before, after, predicted = map(float, m.groups())
    assert after < before / 100 and predicted / 3 < after < 3 * predicted
    per = s["per_coordinate_rms_after"]
    assert s["orientation_rms_after_deg"] == pytest.approx(math.hypot(per["phi_deg"], per["theta_deg"]), rel=1e-9)
    assert "position_rms_after_mm" not in s
    assert "orientation error" in (tmp_path / "d" / "report.html").read_text()


def test_mixed_task_gets_both_units(tmp_path, capsys):
    line, s = _demo(CORPUS / "reachy_mini", tmp_path / "d", capsys)
    assert re.search(r"position error .* mm RMS \(predicted [\d.]+\); orientation error .* deg RMS", line), line
    per = s["per_coordinate_rms_after"]
    assert s["position_rms_after_mm"] == pytest.approx(math.sqrt(sum(per[c] ** 2 for c in ("x_mm", "y_mm", "z_mm"))),
                                                       rel=1e-9)
    assert s["orientation_rms_after_deg"] == pytest.approx(
        math.sqrt(sum(per[c] ** 2 for c in ("rx_deg", "ry_deg", "rz_deg"))), rel=1e-9)
    for fam, u in (("position", "mm"), ("orientation", "deg")):
        lo, hi = s[f"{fam}_predicted_band_{u}"]
        predicted, law = s[f"{fam}_rms_predicted_{u}"], s[f"{fam}_predicted_law_{u}2"]
        assert lo < predicted < hi
        assert sum(law) == pytest.approx(predicted ** 2, rel=0.002)     # the weights that carry 99.9 %
        assert s[f"{fam}_predicted_directions"] >= 1.0
    report = (tmp_path / "d" / "report.html").read_text()
    assert report.count("90 % of campaigns like this one end between") == 2
