"""``pmcal diagnose`` and ``pmcal demo --hidden-effect`` for the over-constrained PM.

Reads and validates the measurements, runs :func:`pmcal.calib.ocpm.diagnose.diagnose`, writes the
diagnosis JSON (docs/formats.md, "Diagnosis JSON"; atomically) and, with ``--report DIR``, a
self-contained HTML report (:mod:`pmcal.reports.ocpm.diagnose`, docs/reports.md), the diagnosed model
(``params.json``: geometry plus the named effects) and the JSON, as one directory that appears whole or
not at all. The demo hides an effect in a twin campaign and diagnoses it without being told.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pmcal.mechanism.ocpm.config import Geometry, default_geometry
from pmcal.calib.ocpm.diagnose import BASELINES, DiagnoseOptions, diagnose as run_diagnosis
from pmcal.calib.ocpm.diagnosis_result import Diagnosis
from pmcal.calib.ocpm.fullchain import UnassembledError
from pmcal.calib.ocpm.registration import FRAME_KEYS, FrameCorrected
from pmcal.apps.ocpm.diagnose_frame import frame_input
from pmcal.mechanism.ocpm.effects import EFFECT_NAMES
from pmcal.twin.ocpm.effect_model import EffectChainModel
from pmcal import progress
from pmcal.errors import InputError, RunError
from pmcal.fileio import atomic_directory, write_json
from pmcal.ocpm.io import MECHANISM, check_context, read_params, write_measurements, write_params
from pmcal.reports.ocpm.diagnose import effect_label, report

#: Fewest poses the diagnosis accepts: the baseline has 31 parameters and cross-validation holds out
#: a tenth of the poses.
MIN_POSES = 24


# ====================================================================== input
def check_sigma(sigma: float | None) -> float | None:
    if sigma is None:
        return None
    if not (np.isfinite(sigma) and sigma > 0):
        raise InputError(f"tracker noise must be a positive number of mm, got {sigma}", field="--sigma")
    return float(sigma)


def load(args, geom: Geometry):
    """Measurements (base frame, complete rows), options and (frame part of the JSON, notes) from the
    command line; InputError naming file, row and field."""
    sigma = check_sigma(args.sigma)
    model = args.model or "full"
    if model not in BASELINES:
        raise InputError(f"unknown model '{model}' (known: {', '.join(BASELINES)})", field="--model")
    meas, frame_doc, frame_notes = frame_input(args, geom, sigma, MIN_POSES)
    if len(meas) < MIN_POSES:
        raise InputError(f"{len(meas)} poses are too few to tell an effect from the geometry: measure at least "
                         f"{MIN_POSES} (the diagnosis campaign has 128)", file=args.measurements, field="pose_id")
    check_context(args.measurements, meas.approach, meas.temp_c)
    initial = None
    if args.params:
        initial, _ = read_params(args.params, geom)
    options = DiagnoseOptions(baseline_keys=BASELINES[model], sigma_mm=sigma, initial=initial,
                              fit_stiffness_ratio=model == "full")
    if frame_doc.get("frame") == "tracker":
        from pmcal.ocpm.tracker_frame import with_frame_correction

        options = with_frame_correction(options)
    return meas, options, (frame_doc, frame_notes)


def run(meas, options: DiagnoseOptions, geom: Geometry, source: str | None = None) -> Diagnosis:
    """The diagnosis with a progress bar over its steps. A measured pose the model cannot assemble at the
    start (outside the workspace) is an InputError naming the file and the rows."""
    steps = ["fitting the baseline model", "testing candidate effects", "cross-validating"]
    with progress.progress(total=len(steps), desc="diagnose", unit="step") as bar:
        def on_step(text: str) -> None:
            bar.set_description(text)
            if text in steps:
                bar.update(1)
        try:
            model = EffectChainModel(geom)
            if any(k in FRAME_KEYS for k in options.baseline_keys or ()):
                model = FrameCorrected(model)          # tracker frame: the registration stays in the baseline
            return run_diagnosis(meas, model, options, on_step)
        except UnassembledError as exc:
            raise InputError(str(exc), file=source) from None
        except (RuntimeError, np.linalg.LinAlgError) as exc:
            raise RunError(f"the diagnosis failed: {exc}") from None


# ====================================================================== outputs
def document(d: Diagnosis, source: str, model: str) -> dict:
    doc = d.to_json()
    doc.update({"mechanism": MECHANISM, "measurements": source, "baseline_model": model})
    return doc


def write_outputs(d: Diagnosis, doc: dict, json_path: str, report_dir: str | None, title: str,
                  extra=None) -> None:
    """JSON (atomic) and report directory (atomic); the report first so a failure leaves neither."""
    if report_dir is None:
        write_json(json_path, doc)
        return
    with atomic_directory(report_dir) as tmp:
        report(d, title, extra).write(tmp / "index.html")          # pmcal.reports.ocpm.diagnose
        write_params(tmp / "params.json", {k: v for k, v in d.params().items() if k not in FRAME_KEYS},
                     model="full-chain + effects",
                     stiffness_ratio=d.final.info["stiffness_ratio"],
                     effects={v.name: {"value": v.value, "interval": list(v.interval), "unit": v.unit,
                                       "params": {k: p[0] for k, p in v.params.items()}} for v in d.named},
                     source="pmcal diagnose")
        write_json(tmp / "diagnosis.json", doc)
        write_json(json_path, doc)


def summary_line(d: Diagnosis) -> str:
    """The verdict as a plain sentence first, the numbers after it."""
    if d.named:
        verdict = "missing effect: " + ", ".join(f"{effect_label(v)} = {v.value:.4g} {v.unit}" for v in d.named)
        if d.unexplained:
            verdict += "; structure left that no candidate explains"
        elif d.found_unnamed:
            verdict += "; significant but not named: " + ", ".join(
                f"{c.name} (p = {c.p_value:.2g}, {c.verdict})" for c in d.found_unnamed)
    elif d.unexplained:
        verdict = "missing effect not identified: structure is left that no candidate effect explains"
    elif d.found_unnamed:
        verdict = "no effect named, but significant: " + ", ".join(
            f"{c.name} (p = {c.p_value:.2g}, {c.verdict})" for c in d.found_unnamed)
    else:
        verdict = "no missing effect: the model explains the data to the noise level"
    left = f", {len(d.extrapolated)} extrapolated pose(s) left out" if d.extrapolated else ""
    return (f"{verdict}; held-out gap {d.gap_before:.4f} -> {d.gap_after:.4f} mm "
            f"(noise {d.noise_floor:.4f} mm{left})")


def diagnose(args) -> int:
    geom = default_geometry()
    meas, options, (frame_doc, frame_notes) = load(args, geom)
    d = run(meas, options, geom, str(args.measurements))
    d.notes[:0] = frame_notes
    if frame_doc.get("frame") == "tracker":
        from pmcal.ocpm.tracker_frame import final_registration

        frame_doc = final_registration(frame_doc, d.final)
    doc = document(d, str(args.measurements), args.model or "full")
    if frame_doc:
        doc["measurement_frame"] = frame_doc
    write_outputs(d, doc, args.json, args.report, f"Discrepancy diagnosis: {Path(args.measurements).name}")
    print(summary_line(d))
    return 0


# ====================================================================== hidden-effect demo
def hidden_effect_demo(args) -> int:
    """Hide an effect (a vocabulary name, ``none`` or ``random``) in a twin campaign, diagnose it blind,
    and write measurements, diagnosis, report and the answer into ``args.out``."""
    from pmcal.apps.ocpm.effect_scenarios import REALISTIC, hidden_effect_campaign

    name = args.hidden_effect
    choices = list(EFFECT_NAMES) + ["none", "random"]
    if name not in choices:
        raise InputError(f"unknown effect '{name}' (known: {', '.join(choices)})", field="--hidden-effect")
    seed = int(args.seed)
    if name == "random":
        name = str(np.random.default_rng(seed).choice(list(EFFECT_NAMES) + ["none"]))
    hidden = [] if name == "none" else [name]
    n = int(getattr(args, "poses", None) or 128)
    progress.status(f"measuring a {n}-pose campaign on the twin with a hidden effect (seed {seed})")
    meas, twin = hidden_effect_campaign(hidden, seed, n)
    geom = default_geometry()
    d = run(meas, DiagnoseOptions(), geom)                     # sigma estimated: the analyst is not told
    truth = {"hidden_effect": name if hidden else None, "effects": twin.effects.values(),
             "passive_errors": twin.passive_errors, "geometric_errors": twin.params, "seed": seed,
             "realistic_sizes": REALISTIC}
    right = (set(d.effects) == set(hidden))
    doc = document(d, "measurements.csv", "full")
    out = Path(args.out)
    answer = ["The effect hidden in the campaign: " + (f"{name} {twin.effects.values()[name]}" if hidden else "none"),
              f"Diagnosis: {', '.join(d.effects) or 'no effect'} "
              f"({'right' if right else 'WRONG'})"]
    with atomic_directory(out) as tmp:
        write_measurements(tmp / "measurements.csv", meas, comments=[
            f"pmcal demo --hidden-effect: twin campaign, seed {seed}; the effect is in answer.json",
            "units: mm, deg; targets in the base frame O-xyz"])
        write_outputs(d, doc, str(tmp / "diagnosis.json"), str(tmp / "report"),
                      "pmcal demo: a hidden effect, diagnosed blind", extra=answer)
        write_json(tmp / "answer.json", truth)
    print(f"hidden: {name}; diagnosed: {', '.join(d.effects) or 'none'} ({summary_line(d)})", flush=True)       # the answer: answer.json
    return 0
