"""The independent simulator (tests/crosssim) against closed forms and the twin, and the diagnosis on its data.

Tolerances: the nominal machine is exact (seed eq. 7) to solver precision. With errors, the two models
differ only in how the over-constraint compromise is formulated (here: weighted closure residuals; twin:
3-D springs at S_j) and in the gravity load; the difference is bounded by the passive gap (~1 mm) over the
stiffness ratio (1000) plus the gravity sag (<= 0.025 mm, of which the formulations share the bulk):
measured <= 0.0005 mm without and <= 0.002 mm with gravity; asserted at 0.002 / 0.005 mm (0.2 / 0.5 sigma).
"""

import numpy as np
import pytest

from crosssim.campaign import SimEffects, drift_offsets, hidden_campaign, plan, random_errors, simulate, write_csv
from crosssim.machine import H_SS, ClosedChain, Geometry, nominal_ik, tilt_torsion


@pytest.mark.parametrize("phi,theta", [(0, 0), (30, 45), (200, 80), (123, 60), (300, 72)])
def test_nominal_machine_matches_eq7(phi, theta):
    b = nominal_ik(phi, theta)
    r, R, beta, energy = ClosedChain(Geometry(), gravity=False).solve(np.deg2rad(b[:2]), (phi + 3, 0.9 * theta))
    p, t = np.deg2rad([phi, theta])
    r7 = H_SS * np.array([np.cos(p) * np.sin(t / 2), np.sin(p) * np.sin(t / 2), np.cos(t / 2)])
    assert np.abs(r - r7).max() < 1e-9 and np.abs(R - tilt_torsion(p, t)).max() < 1e-12
    assert np.abs(np.rad2deg(beta) - b).max() < 1e-9 and energy < 1e-12


def test_home_angle():
    assert nominal_ik(0, 0) == pytest.approx([-39.351] * 4, abs=1e-3)


@pytest.mark.parametrize("limbs,gravity,tol", [((1, 2), False, 0.002), ((1, 2, 3, 4), False, 0.002),
                                               ((1, 2, 3, 4), True, 0.005)])
def test_agrees_with_twin_under_errors(limbs, gravity, tol):
    from pmcal.twin.ocpm.effects import Effects, EffectTwin
    from pmcal.twin.ocpm.machine import Twin

    rng = np.random.default_rng(3)
    err = random_errors(rng, 0.5, limbs)
    s = simulate(plan(24, 80, rng, block=5), err, SimEffects(), sigma_mm=0, gravity=gravity)
    if gravity:
        st = EffectTwin(err, Effects(), gravity=True).reach(s.cmd_deg, payload_kg=s.payload_kg)
    else:
        st = Twin(err).reach(s.cmd_deg)
    assert len(s.cmd_deg) >= 20
    assert np.linalg.norm(st.targets - s.targets, axis=2).max() < tol


def test_backlash_follows_move_order():
    from crosssim.campaign import drive_angles

    c = plan(6, 40, np.random.default_rng(0), temp_range=(20, 20), payloads=(0,))
    c.cmd_deg = np.array([[-30, -30], [-20, -40], [-20, -35], [-25, -35], [-10, -50], [-10, -50.0]])
    d = np.rad2deg(drive_angles(c, Geometry(), SimEffects(backlash=(0.02, 0.03)))) - c.cmd_deg
    assert d[:, 0] == pytest.approx([-0.02, -0.02, -0.02, 0.02, -0.02, -0.02])
    assert d[:, 1] == pytest.approx([-0.03, 0.03, -0.03, -0.03, 0.03, 0.03])


def _diagnose(tmp_path, names, seed=1, sizes=None, forms=None, truth=False):
    from pmcal.calib.ocpm.diagnose import DiagnoseOptions, diagnose
    from pmcal.ocpm.io import read_measurements
    from pmcal.twin.ocpm.effect_model import EffectChainModel

    camp, _, fx = hidden_campaign(names, seed, sizes=sizes, forms=forms)
    write_csv(tmp_path / "m.csv", camp)
    meas = read_measurements(tmp_path / "m.csv")
    assert meas.approach is None
    d = diagnose(meas, EffectChainModel(), DiagnoseOptions(sigma_mm=0.01))
    return (d, fx, camp) if truth else d


@pytest.mark.parametrize("name", ["backlash", "zero_offset_drift", "encoder_eccentricity", "joint_compliance",
                                  "overconstraint", "thermal_expansion"])
def test_diagnosis_names_crosssim_effect(tmp_path, name):
    """128 poses to 80 deg in time order, no approach columns, warm-up/cool-down: the family is named
    (eccentricity at 0.02 deg, twice its realistic size, where one seed decides reliably; the naming rate
    at 0.01 deg is the benchmark's job)."""
    d = _diagnose(tmp_path, [name], sizes={"encoder_eccentricity": 0.02})
    assert d.effects == [name]
    assert any("approach inferred" in n for n in d.notes)
    if name != "thermal_expansion":   # links-only expansion is not the uniform member (documented)
        assert d.gap_after < 1.2 * d.noise_floor


def test_two_effects_at_once_are_both_named(tmp_path):
    """Errors in every limb (1.5 mm / 0.3 deg passive-limb errors: a large, nonlinear over-constraint) and
    encoder eccentricity at its realistic 0.01 deg: both named. With the folds linearised at the baseline
    the over-constraint counted as leftover structure in every fold and eccentricity was "not confirmed on
    held-out poses" (0 of 10 folds, this seed); each fold now tests it at the model already named."""
    d = _diagnose(tmp_path, ["overconstraint", "encoder_eccentricity"], seed=1002, sizes={"overconstraint": 1.5})
    assert sorted(d.effects) == ["encoder_eccentricity", "overconstraint"]
    assert d.candidates["encoder_eccentricity"].cv_folds >= 8
    assert d.gap_after < 1.2 * d.noise_floor


def test_diagnosis_clean_crosssim(tmp_path):
    d = _diagnose(tmp_path, [])
    assert d.effects == [] and not d.unexplained


def test_lone_edge_pose_is_left_out_of_the_held_out_gap(tmp_path):
    """A clean campaign drawn uniformly on the cap (seed 1055) has one pose at 73.8 deg tilt alone in its
    region (X107, leverage ~1.7 of the model's directions); held out, it is predicted ~0.14 mm off, which
    put the held-out gap at 1.6 sigma with nothing to name. The diagnosis names it in a note and takes the
    gaps without it (about 1.0 sigma; the RMS of ~1100 whitened residuals scatters by ~2 %); the gap over
    every pose stays in the result."""
    d = _diagnose(tmp_path, [], seed=1055)
    assert d.effects == [] and not d.unexplained
    assert "X107" in d.extrapolated and len(d.extrapolated) <= 3
    assert d.gap_after <= 1.1 * d.noise_floor and d.gap_after_all > 1.4 * d.noise_floor
    assert any(n.startswith("left out of the held-out gaps: X107") for n in d.notes)
    doc = d.to_json()
    assert doc["extrapolated_poses"] == d.extrapolated and doc["gap_after_all_poses"] == d.gap_after_all


def test_unexplained_structure_is_characterised(tmp_path):
    """A tracker stand creeping 0.004 mm/K along x is no effect of the vocabulary: the diagnosis names
    nothing, and says the residual follows the temperature (not the time: warm-up then cool-down)."""
    from pmcal.calib.ocpm.diagnose import DiagnoseOptions, diagnose
    from pmcal.ocpm.io import read_measurements
    from pmcal.twin.ocpm.effect_model import EffectChainModel

    camp, _, _ = hidden_campaign([], 5)
    camp.targets[:, :, 0] += 0.004 * (camp.temp_c - 18.0)[:, None]
    write_csv(tmp_path / "m.csv", camp)
    d = diagnose(read_measurements(tmp_path / "m.csv"), EffectChainModel(), DiagnoseOptions(sigma_mm=0.01))
    assert d.effects == [] and d.unexplained
    top = d.unexplained_context[0]
    assert top.context == "temperature" and top.p_value < 1e-6 and top.direction.endswith("_x")
    assert d.to_json()["unexplained_context"][0]["context"] == "temperature"


def test_small_campaign_names_what_it_can_and_advises(tmp_path):
    """48 poses to 60 deg (cross-sim, backlash): backlash is named; encoder eccentricity is honestly not
    identifiable there, and the advice names the campaign that would make it so. `pmcal twin plan
    --for-diagnosis --from DIAG.json` writes that campaign's command list with the advice."""
    import csv
    import json

    from pmcal.cli import main

    camp, _, _ = hidden_campaign(["backlash"], 1, n=48, theta_max_deg=60)
    write_csv(tmp_path / "m.csv", camp)
    assert main(["diagnose", str(tmp_path / "m.csv"), "--json", str(tmp_path / "d.json"), "--sigma", "0.01"]) == 0
    doc = json.loads((tmp_path / "d.json").read_text())
    assert doc["effects"] == ["backlash"]
    ecc = next(c for c in doc["candidates"] if c["name"] == "encoder_eccentricity")
    assert ecc["verdict"].startswith("not identifiable") and "theta up to 85" in ecc["fix"]
    out = tmp_path / "plan.csv"
    assert main(["twin", "plan", "--for-diagnosis", "--from", str(tmp_path / "d.json"), "-o", str(out)]) == 0
    text = out.read_text()
    assert "not identifiable in the last campaign: encoder_eccentricity" in text
    rows = list(csv.DictReader(line for line in text.splitlines() if not line.startswith("#")))
    assert len(rows) == 128 and max(float(r["theta_deg"]) for r in rows) <= 80.0
    # the plan moves every motor both ways and its temperature is not monotone in time
    for m in ("m1_approach", "m2_approach"):
        assert {r[m] for r in rows} == {"1", "-1"}
    temp = np.array([float(r["temp_c_planned"]) for r in rows])
    assert np.argmax(temp) not in (0, len(temp) - 1)


@pytest.mark.parametrize("name", ["zero_offset_drift", "thermal_expansion", "overconstraint", "joint_compliance",
                                  "encoder_eccentricity"])
def test_small_campaign_names_every_identifiable_effect(tmp_path, name):
    """48 poses to 60 deg (cross-sim, seed 1), one effect at a time: drift, thermal expansion,
    over-constraint and compliance are named and close the held-out gap; eccentricity is not identifiable
    there (nothing named, nothing left unexplained) and the advice says which campaign would see it."""
    from pmcal.calib.ocpm.diagnose import DiagnoseOptions, diagnose
    from pmcal.ocpm.io import read_measurements
    from pmcal.twin.ocpm.effect_model import EffectChainModel

    camp, _, _ = hidden_campaign([name], 1, n=48, theta_max_deg=60)
    write_csv(tmp_path / "m.csv", camp)
    d = diagnose(read_measurements(tmp_path / "m.csv"), EffectChainModel(), DiagnoseOptions(sigma_mm=0.01))
    ecc = d.candidates["encoder_eccentricity"]
    assert ecc.verdict == "not identifiable with this campaign" and "theta up to 85" in ecc.fix
    if name == "encoder_eccentricity":
        assert d.effects == [] and not d.unexplained
    else:
        assert d.effects == [name]
        assert d.gap_after < 1.2 * d.noise_floor


def test_plan_rejects_bad_input(tmp_path, capsys):
    from pmcal.cli import main

    assert main(["twin", "plan", "--for-diagnosis", "--poses", "5", "-o", str(tmp_path / "p.csv")]) == 2
    assert "--poses" in capsys.readouterr().err and not (tmp_path / "p.csv").exists()


def test_inferred_approach_matches_the_simulated_move_order():
    """pmcal's approach from the row order equals the simulator's own move signs (rows 2..N)."""
    from crosssim.campaign import drive_angles

    from pmcal.mechanism.ocpm.effects import approach_from_order

    c = plan(60, 70, np.random.default_rng(4))
    c.cmd_deg[10] = c.cmd_deg[9]          # a row that does not move: the sign carries over
    lag = np.rad2deg(drive_angles(c, Geometry(), SimEffects(backlash=(1.0, 1.0)))) - c.cmd_deg
    s = approach_from_order(c.cmd_deg)
    assert s[0].tolist() == [0, 0]
    np.testing.assert_array_equal(s[1:], -np.round(lag[1:]))


def test_floor_slide_is_named_frame_drift(tmp_path):
    """The machine slides on its floor during the campaign ((0.15, -0.10, 0.05) mm and a few thousandths of
    a degree over 64 min, the simulator's rotation-vector form): named frame_drift (not over-constraint),
    the held-out gap closes to the noise, and the translation rate of the base origin lies in its 95 %
    interval; the note advises re-measuring the reference nests."""
    d, fx, camp = _diagnose(tmp_path, ["frame_drift"], seed=1000, truth=True)
    assert d.effects == ["frame_drift"] and not d.unexplained
    assert d.gap_after < 1.2 * d.noise_floor < d.gap_before
    hours = (camp.time_s[-1] - camp.time_s[0]) / 3600.0
    lo, hi = d.named[0].interval
    assert lo <= np.linalg.norm(fx.frame_drift[:3]) / hours <= hi
    assert "reference nests" in d.candidates["frame_drift"].fix


def test_one_motor_backlash_is_reported_per_motor(tmp_path):
    """Backlash on one motor only (the simulator's lag b from the move order): the headline names that
    motor, and each motor's full dead band 2 b lies in its 95 % interval (the other motor's 0 too)."""
    from pmcal.reports.ocpm.diagnose import effect_label

    d, fx, _ = _diagnose(tmp_path, ["backlash"], seed=1000, forms={"backlash": "one motor"}, truth=True)
    assert d.effects == ["backlash"]
    v = d.named[0]
    carrier = 1 + int(np.argmax(fx.backlash))
    assert v.motors == (carrier,) and effect_label(v) == f"backlash (motor {carrier})"
    for m in v.per_motor:
        lo, hi = m["interval"]
        assert lo <= 2 * fx.backlash[m["motor"] - 1] <= hi, m
    assert v.value == pytest.approx(v.per_motor[carrier - 1]["value"])
    doc = d.to_json()["named"][0]
    assert {"name", "value", "interval", "unit"} <= set(doc) and doc["motors"] == [carrier]


def test_one_motor_drift_is_reported_per_motor(tmp_path):
    """Drift on one motor only, the simulator's exponential creep (tau = 2 h, seed 1013): the headline names
    that motor, and each motor's campaign-mean rate (the drift from the first row the diagnosis fits to the
    last over that time) holds the simulator's own in its 95 % interval, 0 for the other motor. The rate at the first
    pose, what the family's quadratic cannot pin down for a creep, is reported beside it as shape; judged
    by it, this seed put drift on both motors."""
    d, fx, camp = _diagnose(tmp_path, ["zero_offset_drift"], seed=1013, forms={"zero_offset_drift": "one motor"},
                            truth=True)
    assert d.effects == ["zero_offset_drift"]
    v = d.named[0]
    carrier = 1 + int(np.argmax(np.abs(fx.drift)))
    assert v.motors == (carrier,)
    i = np.searchsorted(camp.time_s, d.meas.time_s[[0, -1]])      # the rows the diagnosis fits (not the first)
    off = drift_offsets(camp.time_s, fx)
    true = (off[i[1]] - off[i[0]]) * 3600.0 / (camp.time_s[i[1]] - camp.time_s[i[0]])
    for m in v.per_motor:
        lo, hi = m["interval"]
        assert lo <= true[m["motor"] - 1] <= hi, m
        assert {"rate_first_pose", "curvature", "form_allowance"} <= set(m)
    assert v.value == pytest.approx(abs(v.per_motor[carrier - 1]["value"]))
    lo, hi = v.interval
    assert lo <= abs(true[carrier - 1]) <= hi


def test_parts_expanding_at_their_own_rates(tmp_path):
    """Aluminium cranks and couplers (23e-6/K), a steel strut and base (12e-6/K), a platform at 17e-6/K
    (nests on it): named thermal_expansion; every part the campaign determines (std <= 2.5e-6/K) holds its
    true rate within 3 std, and the held-out gap closes to the noise."""
    d, fx, _ = _diagnose(tmp_path, ["thermal_expansion"], seed=1000, forms={"thermal_expansion": "per part"},
                         truth=True)
    assert d.effects == ["thermal_expansion"] and d.gap_after < 1.2 * d.noise_floor
    v = d.named[0]
    assert v.parts and any(p["separable"] for p in v.parts)
    for p in v.parts:
        if p["separable"]:
            truth = np.mean([fx.thermal_parts[k] for k in p["parts"]])
            assert abs(p["rate"] - truth) <= 3 * p["std"] + 0.5 * np.ptp([fx.thermal_parts[k] for k in p["parts"]])
    assert any(n.startswith("thermal_expansion by part") for n in d.notes)


def test_an_effect_no_family_holds_is_not_given_the_nearest_name(tmp_path):
    """Target nest 1 sagging under gravity (0.1 mm across its arm, pose dependent): the passive-limb geometry
    absorbs a significant part of it (the selection and 10 of 10 folds pick over-constraint), but on the
    held-out poses it removes less than half of the structure beyond the noise: nothing is named, the
    structure is reported unexplained with what it follows."""
    d = _diagnose(tmp_path, ["nest_sag"], seed=1000)
    assert d.effects == [] and d.unexplained and d.unexplained_context
    oc = d.candidates["overconstraint"]
    assert oc.verdict == "explains only part of the structure" and oc.held_out_share < 0.5
    doc = next(c for c in d.to_json()["candidates"] if c["name"] == "overconstraint")
    assert doc["held_out_share"] == pytest.approx(oc.held_out_share)


def test_a_shape_two_families_share_does_not_earn_their_names(tmp_path):
    """A tracker range error growing with the distance (6e-5 d^2/2500 mm, no family holds it): passive-limb
    geometry and thermal parts together fit it to the noise (the omnibus test finds nothing left after
    both), so it was named over-constraint + thermal. Held out, each explains only part of it, clearly
    measured: thermal 59 % (a measured share needs 75 %), then over-constraint alone 77 % with structure
    left (it needs 90 % then): nothing is named, the structure is reported unexplained with what it
    follows; the share with whole workspace regions held out is reported beside it."""
    d = _diagnose(tmp_path, ["tracker_scale"], seed=1000)
    assert d.effects == [] and d.unexplained and d.unexplained_context
    for name in ("overconstraint", "thermal_expansion"):
        c = d.candidates[name]
        assert c.verdict == "explains only part of the structure" and c.reason.startswith("on held-out poses")
        assert c.held_out_share < 0.8 and np.isfinite(c.transfer_share)
    doc = {c["name"]: c for c in d.to_json()["candidates"]}
    assert doc["overconstraint"]["transfer_share"] == pytest.approx(d.candidates["overconstraint"].transfer_share)
