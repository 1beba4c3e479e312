"""``pmcal diagnose`` and ``pmcal demo --hidden-effect`` for the over-constrained PM.

Reads and validates the measurements, runs :func:`pmcal.calib.ocpm.diagnose.diagnose`, writes the JSON of
INTERFACES.md (atomically) and, with ``--report DIR``, a self-contained HTML report, the diagnosed model
(``params.json``: geometry plus the named effects) and the JSON, as one directory that appears whole or
not at all. The demo hides an effect in a twin campaign and diagnoses it without being told.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pmcal.mechanism.ocpm.config import Geometry, default_geometry
from pmcal.calib.ocpm.diagnose import BASELINES, DiagnoseOptions, diagnose as run_diagnosis
from pmcal.calib.ocpm.diagnosis_result import Diagnosis
from pmcal.calib.ocpm.registration import FRAME_KEYS, FrameCorrected
from pmcal.apps.ocpm_diagnose_frame import frame_input
from pmcal.mechanism.ocpm.effects import EFFECT_NAMES, VOCABULARY
from pmcal.mechanism.ocpm.params import errors_and_ratio
from pmcal.twin.effect_model import EffectChainModel
from pmcal import progress
from pmcal.errors import InputError, RunError
from pmcal.fileio import atomic_directory, write_json
from pmcal.io_ocpm import MECHANISM, read_params, write_measurements, write_params

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
    if meas.approach is not None:
        bad = np.argwhere(~np.isin(meas.approach, (-1.0, 1.0)))
        if bad.size:
            i, j = (int(v) for v in bad[0])
            raise InputError(f"approach must be +1 or -1, got {meas.approach[i, j]:g}", file=args.measurements,
                             row=i + 1, field=f"m{j + 1}_approach")
    if meas.temp_c is not None:
        bad = np.flatnonzero(~np.isfinite(meas.temp_c))
        if 0 < bad.size < len(meas):
            raise InputError("temperature missing in some rows (give it for every pose or for none)",
                             file=args.measurements, row=int(bad[0]) + 1, field="temp_c")
        if np.any(np.abs(meas.temp_c[np.isfinite(meas.temp_c)] - 20.0) > 60.0):
            i = int(np.flatnonzero(np.abs(meas.temp_c - 20.0) > 60.0)[0])
            raise InputError(f"temperature {meas.temp_c[i]:g} degC is implausible for a machine in use "
                             "(degrees Fahrenheit or kelvin?)", file=args.measurements, row=i + 1, field="temp_c")
    initial = None
    if args.params:
        initial, _ = read_params(args.params, geom)
    options = DiagnoseOptions(baseline_keys=BASELINES[model], sigma_mm=sigma, initial=initial,
                              fit_stiffness_ratio=model == "full")
    if frame_doc.get("frame") == "tracker":
        from pmcal.tracker_frame import with_frame_correction

        options = with_frame_correction(options)
    return meas, options, (frame_doc, frame_notes)


def run(meas, options: DiagnoseOptions, geom: Geometry) -> Diagnosis:
    """The diagnosis with a progress bar over its steps."""
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
        report(d, title, extra).write(tmp / "index.html")
        write_params(tmp / "params.json", {k: v for k, v in d.params().items() if k not in FRAME_KEYS},
                     model="full-chain + effects",
                     stiffness_ratio=d.final.info["stiffness_ratio"],
                     effects={v.name: {"value": v.value, "interval": list(v.interval), "unit": v.unit,
                                       "params": {k: p[0] for k, p in v.params.items()}} for v in d.named},
                     source="pmcal diagnose")
        write_json(tmp / "diagnosis.json", doc)
        write_json(json_path, doc)


def summary_line(d: Diagnosis) -> str:
    if d.named:
        named = ", ".join(f"{v.name} = {v.value:.4g} {v.unit}" for v in d.named)
    else:
        named = "no effect named"
    extra = "; structure left that no candidate explains" if d.unexplained else ""
    return (f"{named}{extra}; held-out gap {d.gap_before:.4f} -> {d.gap_after:.4f} mm "
            f"(noise {d.noise_floor:.4f} mm)")


def diagnose(args) -> int:
    geom = default_geometry()
    meas, options, (frame_doc, frame_notes) = load(args, geom)
    d = run(meas, options, geom)
    d.notes[:0] = frame_notes
    if frame_doc.get("frame") == "tracker":
        from pmcal.tracker_frame import final_registration

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
    from pmcal.apps.effect_scenarios import REALISTIC, hidden_effect_campaign

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
    print(f"hidden: {name}; diagnosed: {summary_line(d)}; written {out}/")
    return 0


# ====================================================================== report
def report(d: Diagnosis, title: str, extra=None):
    """The HTML report: verdicts, scoreboard, held-out gaps, context plots, added-variable plots,
    per-pose residual arrows, the diagnosed model."""
    from pmcal.reports.html import Report, matplotlib_agg

    matplotlib_agg()
    meas = d.meas
    rep = Report(title, f"{len(meas)} poses; tracker noise {d.noise.sigma_mm:.4g} mm ({d.noise.source}); "
                        f"baseline: whole-chain geometric model ({len(d.baseline.names)} parameters); "
                        f"{len(np.unique(d.folds))}-fold cross-validation; {d.runtime_s:.1f} s")
    if extra:
        rep.card("Demo", extra, "warn")
    _verdict_cards(rep, d)
    rep.heading("Scoreboard of the candidate effects")
    rep.paragraph("Every effect of the vocabulary, tested against the baseline (and the effects already "
                  "named): survival = share of a typical-size signature the geometric parameters cannot "
                  "absorb; power = chance to detect a typical size with this campaign; the test is a "
                  "pose-clustered Wald test (F), Bonferroni-corrected; share = part of the structure left "
                  "beyond the noise that the effect explains; folds = cross-validation folds whose own "
                  "selection picked it.", "note")
    rows = []
    for c in d.candidates.values():
        v = c.value
        val = "–" if v is None else f"{v.value:.4g} [{_f(v.interval[0])}, {_f(v.interval[1])}] {v.unit}"
        rows.append([c.name, VOCABULARY[c.name].layer, c.verdict, _pct(c.survival), _f(c.power_typical, 2),
                     _f(c.delta_chi2, 4), c.nu, _f(c.F, 3), _f(c.p_value, 2), _f(c.threshold, 2), _pct(c.share),
                     val, f"{c.cv_folds}/{len(np.unique(d.folds))}"])
    rep.table(["effect", "layer", "verdict", "survival", "power", "Δχ²", "dir.", "F", "p", "threshold",
               "share", "value [95 %]", "folds"], rows, left_cols=3)
    reasons = [f"{c.name}: {c.reason}" for c in d.candidates.values() if c.reason]
    if reasons:
        rep.card("Why", reasons)
    fixes = [f"{c.name}: {c.fix}" for c in d.candidates.values() if c.verdict == "not identifiable with this campaign"]
    if fixes:
        rep.card("What measurement would make the unseen effects visible", fixes, "warn")
    _gap_figures(rep, d)
    _context_figures(rep, d)
    _added_variable_figures(rep, d)
    _arrow_figures(rep, d)
    rep.heading("The diagnosed model")
    rep.table(["parameter", "value", "unit"],
              [[k, v, "deg" if k.split(".")[-1] in ("dalpha", "dgamma", "dmu", "dnu", "dtheta") else "mm"]
               for k, v in d.params().items()] +
              [["stiffness ratio", d.final.info["stiffness_ratio"], "–"]] +
              [[f"{v.name}", v.value, v.unit] for v in d.named], left_cols=1)
    return rep


def _f(v, digits: int = 4) -> str:
    if v is None or not np.isfinite(v):
        return "–"
    return f"{v:.{digits}g}"


def _pct(v) -> str:
    return "–" if v is None or not np.isfinite(v) else f"{100 * v:.3g} %"


def _verdict_cards(rep, d: Diagnosis) -> None:
    rep.heading("Verdict")
    head = {"noise": ("What is left is noise: nothing to name", "ok"),
            "named": (f"Named: {', '.join(d.effects)}", "ok"),
            "unexplained": ("Structure left that no candidate explains", "bad"),
            "named+unexplained": (f"Named: {', '.join(d.effects)}; more structure left unexplained", "warn")}[d.verdict]
    rep.card(head[0], [f"held-out gap (RMS over held-out target coordinates): {d.gap_before:.4f} mm before, "
                       f"{d.gap_after:.4f} mm after; noise floor {d.noise_floor:.4f} mm",
                       f"residual / noise: {d.omnibus_before.ratio:.3g} before, {d.omnibus_after.ratio:.3g} after "
                       f"(robust {d.omnibus_after.robust_ratio:.3g})"] + d.notes, head[1])
    for v in d.named:
        info = VOCABULARY[v.name]
        lines = [info.what, f"value {v.value:.5g} {v.unit}, 95 % interval [{_f(v.interval[0], 5)}, "
                            f"{_f(v.interval[1], 5)}] {v.unit}; layer: {info.layer}"]
        lines += [f"{k}: {p[0]:.5g} ± {p[1]:.2g}" for k, p in list(v.params.items())[:6]]
        rep.card(f"{v.name}", lines, "ok")


def _gap_figures(rep, d: Diagnosis) -> None:
    import matplotlib.pyplot as plt

    rep.heading("Held-out disagreement, before and after")
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.4))
    lim = np.percentile(np.abs(d.cv_before), 99.5)
    bins = np.linspace(-lim, lim, 60)
    for a, data, lab in ((ax[0], d.cv_before, f"baseline: {d.gap_before:.4f} mm RMS"),
                         (ax[1], d.cv_after, f"with {', '.join(d.effects) or 'nothing'}: {d.gap_after:.4f} mm RMS")):
        a.hist(np.clip(data.ravel(), -lim, lim), bins=bins, color="#2b6cb0", alpha=0.8, density=True)
        x = np.linspace(-lim, lim, 200)
        s = d.noise_floor
        a.plot(x, np.exp(-0.5 * (x / s) ** 2) / (s * np.sqrt(2 * np.pi)), "k--", lw=1, label="noise")
        a.set_title(lab, fontsize=10)
        a.set_xlabel("held-out residual, mm")
        a.legend(fontsize=8)
    rep.figure(fig, "Held-out residuals of every target coordinate (each pose predicted by the model fitted "
                    "without its fold), with the tracker-noise density")


def _apparent(d: Diagnosis, lin) -> tuple[np.ndarray, np.ndarray]:
    """Per pose: the residual as an apparent motor-angle error (N, 2) deg (least squares on the
    motor-angle sensitivities) and as an apparent scale about O (N,) ppm."""
    N = len(d.meas)
    r = (lin.r * lin.sigma).reshape(N, -1)
    cols = lin.cols(["L1.dtheta", "L2.dtheta"])
    D = (lin.J[:, cols] * lin.sigma / lin.scale[cols]).reshape(N, -1, 2)
    x = np.linalg.solve(np.einsum("nki,nkj->nij", D, D), np.einsum("nki,nk->ni", D, r)[..., None])[..., 0]
    T = d.meas.targets.reshape(N, -1) - r
    scale = np.einsum("nk,nk->n", r, T) / np.einsum("nk,nk->n", T, T)
    return np.rad2deg(x), scale * 1e6


def _context_figures(rep, d: Diagnosis) -> None:
    import matplotlib.pyplot as plt

    from pmcal.twin.effects import motor_torques

    meas = d.meas
    N = len(meas)
    e, log_ratio = errors_and_ratio(list(d.baseline.names), d.baseline.x)
    try:
        tau = motor_torques(e, meas.m_cmd_deg, meas.payload_kg, d.baseline.info["stiffness_ratio"])
    except (RuntimeError, ValueError):
        tau = np.full((N, 2), np.nan)
    rep.heading("Residual against context")
    rep.paragraph("Each pose's residual expressed as an apparent motor-angle error (what a motor offset would "
                  "have to be to explain it) and as an apparent uniform scale about O. Backlash splits by "
                  "approach, drift trends with time, eccentricity follows the motor angle, compliance the "
                  "gravity torque, thermal expansion the temperature.", "note")
    order = np.arange(N)
    t = meas.extra.get("effect_t_rel", order)
    t_lab = "time since first pose, h" if d.time_unit == "h" else "pose order"
    for lin, lab in ((d.lin_before, "baseline"), (d.lin_after, f"with {', '.join(d.effects) or 'nothing'}")):
        motor, scale = _apparent(d, lin)
        fig, ax = plt.subplots(2, 3, figsize=(12, 6.2))
        for j, col in enumerate(("#2b6cb0", "#c05621")):
            ax[0, 0].plot(t, motor[:, j], ".", color=col, label=f"motor {j + 1}")
            ax[0, 2].plot(meas.m_cmd_deg[:, j], motor[:, j], ".", color=col)
            ax[1, 0].plot(tau[:, j], motor[:, j], ".", color=col)
            if meas.approach is not None:
                jitter = 0.08 * np.random.default_rng(j).standard_normal(N)
                ax[0, 1].plot(meas.approach[:, j] + jitter + 0.25 * (j - 0.5), motor[:, j], ".", color=col)
        ax[0, 0].set(xlabel=t_lab, ylabel="apparent motor error, deg")
        ax[0, 0].legend(fontsize=8)
        ax[0, 1].set(xlabel="approach direction (-1, +1)", xticks=[-1, 1])
        ax[0, 2].set(xlabel="motor angle, deg")
        ax[1, 0].set(xlabel="gravity torque at the motor, N m", ylabel="apparent motor error, deg")
        if meas.temp_c is not None:
            ax[1, 1].plot(meas.temp_c, scale, ".", color="#276749")
        ax[1, 1].set(xlabel="temperature, degC", ylabel="apparent scale, ppm")
        if meas.payload_kg is not None:
            ax[1, 2].plot(meas.payload_kg, motor[:, 0], ".", color="#2b6cb0")
            ax[1, 2].plot(meas.payload_kg, motor[:, 1], ".", color="#c05621")
        ax[1, 2].set(xlabel="payload, kg")
        for a in ax.ravel():
            a.grid(alpha=0.3)
        fig.suptitle(lab, fontsize=11)
        fig.tight_layout()
        rep.figure(fig, f"Residual against context ({lab})")


def _added_variable_figures(rep, d: Diagnosis) -> None:
    import matplotlib.pyplot as plt

    if not d.added_variable:
        return
    rep.heading("Added-variable plots")
    rep.paragraph("Per candidate, at the final model: its signature in the direction of its fitted parameters "
                  "with everything the rest of the model can absorb projected out (x) against the residual of "
                  "the model without it (y), every target coordinate (dots) and binned means (line). Along the "
                  "diagonal: the candidate explains that part of the residual; a flat cloud: it does not.", "note")
    names = list(d.added_variable)
    cols = 3
    rows = (len(names) + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(12, 3.4 * rows), squeeze=False)
    for a, name in zip(axes.ravel(), names):
        x, y = d.added_variable[name]
        a.plot(x, y, ".", ms=2, alpha=0.35, color="#718096")
        if np.ptp(x) > 0:
            edges = np.quantile(x, np.linspace(0, 1, 16))
            idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, 14)
            xm = np.array([x[idx == b].mean() if np.any(idx == b) else np.nan for b in range(15)])
            ym = np.array([y[idx == b].mean() if np.any(idx == b) else np.nan for b in range(15)])
            a.plot(xm, ym, "-o", color="#c53030", ms=3)
            lim = np.max(np.abs(x))
            a.plot([-lim, lim], [-lim, lim], "k:", lw=1)
        a.set_title(f"{name} ({d.candidates[name].verdict})", fontsize=9)
        a.set_xlabel("projected signature, mm")
        a.set_ylabel("residual without it, mm")
        a.grid(alpha=0.3)
    for a in axes.ravel()[len(names):]:
        a.axis("off")
    fig.tight_layout()
    rep.figure(fig, "Added-variable plots at the final model")


def _arrow_figures(rep, d: Diagnosis) -> None:
    import matplotlib.pyplot as plt

    meas = d.meas
    N = len(meas)
    _, R, _ = meas.poses()
    theta = np.rad2deg(np.arccos(np.clip(R[:, 2, 2], -1, 1)))
    phi = np.arctan2(R[:, 1, 2], R[:, 0, 2])
    x, y = theta * np.cos(phi), theta * np.sin(phi)
    rep.heading("Per-pose residuals")
    fig, ax = plt.subplots(1, 2, figsize=(11, 5.2))
    before = (d.lin_before.r * d.lin_before.sigma).reshape(N, -1, 3).mean(1)
    after = (d.lin_after.r * d.lin_after.sigma).reshape(N, -1, 3).mean(1)
    scale = max(np.percentile(np.linalg.norm(before[:, :2], axis=1), 95), 1e-9) / 8.0
    zmax = max(float(np.abs(before[:, 2]).max()), 1e-9)
    for a, res, lab in ((ax[0], before, "baseline"), (ax[1], after, f"with {', '.join(d.effects) or 'nothing'}")):
        q = a.quiver(x, y, res[:, 0], res[:, 1], np.abs(res[:, 2]), angles="xy", scale_units="xy", scale=scale,
                     cmap="viridis", width=0.004, clim=(0, zmax))
        fig.colorbar(q, ax=a, shrink=0.7, label="|z| residual, mm")
        a.set_aspect("equal")
        a.set(xlabel="theta cos(phi), deg", ylabel="theta sin(phi), deg", title=lab)
        a.grid(alpha=0.3)
    rep.figure(fig, f"Mean residual of the targets of every pose (x, y as arrows, |z| as colour; arrow scale: "
                    f"{scale:.2g} mm per deg of the plot), placed at the pose's platform normal")
