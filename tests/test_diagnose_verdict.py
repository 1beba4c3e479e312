"""The diagnosis' verdict sentence agrees with its candidate table (issue 31): "no missing effect" only when
no candidate is significant and nothing is left beyond the noise; a candidate significant at its threshold
but not named (held-out share, implausible value, too small) is said so, with its p-value and why."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest

from pmcal.apps.ocpm.diagnosis import summary_line
from pmcal.calib.ocpm.diagnosis_result import UNNAMED_SIGNIFICANT, Candidate, Diagnosis


def _diagnosis(candidates, named=(), unexplained=False):
    d = SimpleNamespace(candidates={c.name: c for c in candidates}, named=list(named), unexplained=unexplained,
                        gap_before=0.012, gap_after=0.011, extrapolated=[], noise_floor=0.01)
    d.found_unnamed = Diagnosis.found_unnamed.fget(d)
    return d


def _candidate(name, verdict, p, threshold=1e-3):
    return Candidate(name, True, reason="why", p_value=p, threshold=threshold, verdict=verdict)


@pytest.mark.parametrize("verdict", UNNAMED_SIGNIFICANT)
def test_a_significant_candidate_is_never_called_no_missing_effect(verdict):
    d = _diagnosis([_candidate("encoder_eccentricity", verdict, 3e-19), _candidate("backlash", "not significant", 0.4)])
    line = summary_line(d)
    assert not line.startswith("no missing effect"), line
    assert line.startswith("no effect named, but significant: encoder_eccentricity (p = 3e-19, " + verdict)
    assert "backlash" not in line.split(";")[0]


def test_no_missing_effect_only_when_nothing_is_significant():
    d = _diagnosis([_candidate("encoder_eccentricity", "not significant", 0.2),
                    _candidate("backlash", "not identifiable with this campaign", math.nan)])
    assert summary_line(d).startswith("no missing effect: the model explains the data to the noise level")
    # a candidate whose verdict says rejected but whose p-value is above its threshold is not "found"
    d = _diagnosis([_candidate("backlash", "explains only part of the structure", 0.05)])
    assert summary_line(d).startswith("no missing effect")


def test_structure_left_is_said_whatever_the_candidates():
    d = _diagnosis([_candidate("encoder_eccentricity", "not confirmed on held-out poses", 1e-9)], unexplained=True)
    assert summary_line(d).startswith("missing effect not identified: structure is left")


def test_a_named_effect_and_a_significant_unnamed_one_are_both_said():
    named = SimpleNamespace(name="zero_offset_drift", value=0.01, unit="deg/h", member=None, motors=(1,))
    d = _diagnosis([_candidate("zero_offset_drift", "named", 1e-30),
                    _candidate("encoder_eccentricity", "not confirmed on held-out poses", 1e-12)], named=[named])
    line = summary_line(d)
    assert line.startswith("missing effect: ") and "; significant but not named: encoder_eccentricity (p = 1e-12" in line


def test_folder_machines_verdict_agrees_with_its_candidates():
    from pmcal.calib.chain_diagnose import ALPHA, ChainDiagnosis

    def dg(candidates, verdict="noise"):
        return ChainDiagnosis(verdict=verdict, named=[], candidates=candidates, gap_before=0.012, gap_after=0.012,
                              noise_mm=0.01, unexplained={}, time_unit="h")

    quiet = dg([{"name": "backlash", "verdict": "not significant", "p_value": 0.3}])
    assert quiet.summary().startswith("nothing beyond the tracker noise")
    found = dg([{"name": "backlash", "verdict": "not significant", "p_value": 0.3},
                {"name": "zero_drift", "verdict": "does not hold on held-out rows (removes 40% of the structure, "
                 "75% needed)", "p_value": ALPHA / 100}])
    line = found.summary()
    assert line.startswith("no effect named, but significant: zero_drift (p = ") and "backlash" not in line
