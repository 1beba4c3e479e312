"""The HTML report of ``pmcal diagnose`` (``DIR/index.html``): verdict, scoreboard, held-out gaps,
residuals against context, added-variable plots, per-pose residuals, the diagnosed model.

Units on every axis: mm and degrees (an apparent scale in ppm, a torque in N m, a temperature in degC,
a payload in kg where those are the context). The report reads the result generically: each named
effect as family name, member (if any), value and unit; each candidate by its name; a layer or verdict
the vocabulary does not know shows as "–". When nothing is named the model after the diagnosis is the
baseline and every before/after figure is drawn once. A context the campaign does not vary (no
temperature or payload column, or one value for every pose) gets no panel; a note says which.
"""

from __future__ import annotations

import math

import numpy as np

from pmcal.mechanism.ocpm.effects import VOCABULARY
from pmcal.mechanism.ocpm.params import errors_and_ratio
from pmcal.reports.html import Report, matplotlib_agg

BLUE, ORANGE, GREEN = "#2b6cb0", "#c05621", "#276749"
_ANGLE_FIELDS = ("dalpha", "dgamma", "dmu", "dnu", "dtheta")
#: identification methods in words (IdentResult.method -> text)
METHODS = {"full-chain-map": "least squares with the tolerance priors (maximum a posteriori)"}


# ====================================================================== labels from the result
def effect_label(v) -> str:
    """``family``, ``family (member)``, and for a per-motor effect the motors that carry it, e.g.
    ``backlash (motor 2)`` (an EffectValue: its ``name`` is the family)."""
    motors = getattr(v, "motors", ())
    parts = ([v.member] if v.member else []) + (
        [f"motor {motors[0]}" if len(motors) == 1 else "both motors"] if getattr(v, "per_motor", None) and motors else [])
    return f"{v.name} ({', '.join(parts)})" if parts else v.name


def named_labels(d) -> str:
    """The named effects, comma-separated, or "nothing"."""
    return ", ".join(effect_label(v) for v in d.named) or ", ".join(d.effects) or "nothing"


def _layer(name: str) -> str:
    info = VOCABULARY.get(name)
    return info.layer if info is not None else "–"


def same_model(d) -> bool:
    """True when the diagnosis named nothing: the final model is the baseline (one figure, not two)."""
    return not d.effects and not d.named


def baseline_description(d) -> str:
    """The baseline geometric model in words, with its parameter count and fitting method."""
    names = list(d.baseline.names)
    kind = ("whole closed chain (both actuated limbs, the passive limbs and the SS limb)"
            if any(k.startswith("SS.") for k in names) else "the paper's per-limb parameters (limbs 1 and 2)")
    method = d.final.method
    return f"{kind}, {len(names)} parameters, fitted by {METHODS.get(method, method or 'least squares')}"


# ====================================================================== the report
def report(d, title: str, extra=None) -> Report:
    """The HTML report of a :class:`pmcal.calib.ocpm.diagnosis_result.Diagnosis`."""
    matplotlib_agg()
    folds = len(np.unique(d.folds))
    rep = Report(title, f"{len(d.meas)} poses; tracker noise {d.noise.sigma_mm:.4g} mm ({d.noise.source}); "
                        f"baseline: {baseline_description(d)}; {folds}-fold cross-validation; "
                        f"{d.runtime_s:.1f} s")
    if extra:
        rep.card("Demo", extra, "warn")
    verdict_cards(rep, d)
    scoreboard(rep, d)
    gap_figures(rep, d)
    context_figures(rep, d)
    added_variable_figures(rep, d)
    arrow_figures(rep, d)
    rep.heading("The diagnosed model")
    rep.table(["parameter", "value", "unit"],
              [[k, v, "deg" if k.split(".")[-1] in _ANGLE_FIELDS else "mm"] for k, v in d.params().items()] +
              [["stiffness ratio", d.final.info["stiffness_ratio"], "–"]] +
              [[effect_label(v), v.value, v.unit] for v in d.named], left_cols=1)
    return rep


def _f(v, digits: int = 4) -> str:
    if v is None or not np.isfinite(v):
        return "–"
    return f"{v:.{digits}g}"


def _pct(v) -> str:
    return "–" if v is None or not np.isfinite(v) else f"{100 * v:.3g} %"


def verdict_cards(rep: Report, d) -> None:
    """The headline box (it names the method whose gaps it reports) and one card per named effect."""
    rep.heading("Verdict")
    named = named_labels(d)
    found = ", ".join(f"{c.name} (p = {c.p_value:.2g}: {c.verdict})" for c in d.found_unnamed)
    head = {"noise": (f"Nothing named; significant but not named: {found}" if found else
                      "What is left is noise: nothing to name", "warn" if found else "ok"),
            "named": (f"Named: {named}", "ok"),
            "unexplained": ("Structure left that no candidate explains", "bad"),
            "named+unexplained": (f"Named: {named}; more structure left unexplained", "warn")
            }.get(d.verdict, (f"Verdict: {d.verdict}", "warn"))
    after = "the same model (nothing named)" if same_model(d) else f"the baseline + {named}"
    rep.card(head[0], [f"method: discrepancy diagnosis against the baseline, {baseline_description(d)}; "
                       f"gaps by {len(np.unique(d.folds))}-fold cross-validation",
                       f"held-out gap (RMS over held-out target coordinates): {d.gap_before:.4f} mm with the "
                       f"baseline, {d.gap_after:.4f} mm with {after}; noise floor {d.noise_floor:.4f} mm"
                       + (f"; {len(d.extrapolated)} pose(s) predicted by extrapolation left out (notes), over "
                          f"every pose {d.gap_before_all:.4f} → {d.gap_after_all:.4f} mm" if d.extrapolated else ""),
                       f"residual / noise: {d.omnibus_before.ratio:.3g} before, {d.omnibus_after.ratio:.3g} after "
                       f"(robust {d.omnibus_after.robust_ratio:.3g})"] + list(d.notes), head[1])
    for v in d.named:
        info = VOCABULARY.get(v.name)
        lines = [info.what] if info is not None else []
        lines += [f"value {_f(v.value, 5)} {v.unit}, 95 % interval [{_f(v.interval[0], 5)}, "
                  f"{_f(v.interval[1], 5)}] {v.unit}; layer: {_layer(v.name)}"]
        if v.member_params:
            lines += [f"member {v.member}: " + "; ".join(
                f"{k} {p[0]:.5g} ± {p[1]:.2g}" for k, p in v.member_params.items())
                + (" 1/K" if v.name == "thermal_expansion" else "")]
        lines += [motor_line(v.name, m) for m in v.per_motor]
        c = d.candidates.get(v.name)
        if c is not None and c.held_out_band is not None:
            lines += [f"held-out test: {held_out_text(c.held_out_band)}"]
            lines += [f"motor {m}'s part alone: {held_out_text(b, motor=True)}"
                      for m, b in getattr(c, "motor_bands", {}).items()]
        if c is not None:
            lines += [f"motor {m}'s part in the named model: p = {p:.2g} (nested test; below the naming level "
                      f"over the motors it carries the effect even where its held-out test cannot tell)"
                      for m, p in getattr(c, "motor_p_values", {}).items() if p is not None and math.isfinite(p)]
        lines += [f"whole family, {k}: {p[0]:.5g} ± {p[1]:.2g}" for k, p in list(v.params.items())[:6]]
        rep.card(effect_label(v), lines, "ok")


def held_out_text(b, motor: bool = False) -> str:
    """The calibrated held-out test in words: the observed share of the held-out excess the effect removes,
    the band it would have were it the truth and the band of a structure of the same size outside it; for
    one motor's part (``motor``) whether it differs from zero (diagnose._attribute_motors)."""
    text = (f"removes {_pct(b.observed)} of the held-out excess; were it the truth {_pct(b.candidate[0])}–"
            f"{_pct(b.candidate[2])} (5–95 %" + ("" if motor else f", needs {_pct(b.need)}")
            + f"), a structure of its size outside it {_pct(b.alternative[0])}–{_pct(b.alternative[2])}: ")
    if motor:
        return text + ("differs from zero" if b.beyond_alternative else "consistent with zero")
    return text + ("consistent with it and not with the alternative" if b.earned else
                   "not consistent with it" if not b.consistent else "not told apart from the alternative")


def motor_line(name: str, m: dict) -> str:
    """One motor's value of a per-motor effect with its 95 % interval (backlash: the full dead band)."""
    what = {"backlash": "dead band (full)", "encoder_eccentricity": "amplitude",
            "zero_offset_drift": "campaign-mean rate"}.get(name, "value")
    text = f"motor {m['motor']}: {what} {_f(m['value'], 4)} [{_f(m['interval'][0], 4)}, {_f(m['interval'][1], 4)}]"
    if "phase_deg" in m:
        text += f", phase {m['phase_deg']:.1f}° [{m['phase_interval'][0]:.1f}, {m['phase_interval'][1]:.1f}]"
    if "rate_first_pose" in m:
        text += (f" (with a form allowance ± {_f(m['form_allowance'], 2)}); shape: rate at the first pose "
                 f"{_f(m['rate_first_pose'], 4)} ± {_f(m['rate_first_pose_std'], 2)}")
    if "curvature" in m:
        text += f", curvature {_f(m['curvature'], 3)} ± {_f(m['curvature_std'], 2)}"
    return text


def _held_out_cell(c) -> str:
    """The scoreboard cell of the calibrated held-out test (shares in %), "–" when it did not run."""
    b = c.held_out_band
    if b is None:
        return "–"
    return (f"{100 * b.observed:.0f} [{100 * b.candidate[0]:.0f}–{100 * b.candidate[2]:.0f}] "
            f"[{100 * b.alternative[0]:.0f}–{100 * b.alternative[2]:.0f}]")


def scoreboard(rep: Report, d) -> None:
    rep.heading("Scoreboard of the candidate effects")
    rep.paragraph("Every effect of the vocabulary, tested against the baseline (and the effects already "
                  "named): survival = share of a typical-size signature the geometric parameters cannot "
                  "absorb; power = chance to detect a typical size with this campaign; the test is a "
                  "pose-clustered Wald test (F) at the candidate's threshold (weighted Bonferroni); share = part of the structure left "
                  "beyond the noise that the effect explains (shown for significant candidates only: p below the threshold); folds = cross-validation folds whose own "
                  "selection picked it; held-out = the calibrated held-out test of a name (the improvement on held-out poses as a share of the held-out excess over the noise, with its 5–95 % band were the effect the truth and that of a structure of the same size outside it; a name needs the first and more than the second, docs/diagnose.md).", "note")
    folds = len(np.unique(d.folds))
    rows = []
    for c in d.candidates.values():
        v = c.value
        val = "–" if v is None else f"{_f(v.value)} [{_f(v.interval[0])}, {_f(v.interval[1])}] {v.unit}"
        rows.append([c.name if v is None else effect_label(v), _layer(c.name), c.verdict, _pct(c.survival),
                     _f(c.power_typical, 2), _f(c.delta_chi2, 4), c.nu, _f(c.F, 3), _f(c.p_value, 2),
                     _f(c.threshold, 2), _pct(c.share) if c.p_value < c.threshold else "–", val, f"{c.cv_folds}/{folds}",
                     _held_out_cell(c)])
    rep.table(["effect", "layer", "verdict", "survival", "power", "Δχ²", "dir.", "F", "p", "threshold",
               "share", "value [95 %]", "folds", "held-out: observed [if true 5–95 %] [alternative 5–95 %]"],
              rows, left_cols=3)
    reasons = [f"{c.name}: {c.reason}" for c in d.candidates.values() if c.reason]
    if reasons:
        rep.card("Why", reasons)
    fixes = [f"{c.name}: {c.fix}" for c in d.candidates.values()
             if c.verdict == "not identifiable with this campaign" and c.fix]
    if fixes:
        rep.card("What measurement would make the unseen effects visible", fixes, "warn")


# ====================================================================== figures
def _states(d):
    """(label, cross-validated residuals, linearization) of the models to draw: one when nothing is named."""
    if same_model(d):
        return [("baseline = result (nothing named)", d.cv_before, d.lin_before)]
    return [("baseline", d.cv_before, d.lin_before), (f"with {named_labels(d)}", d.cv_after, d.lin_after)]


def _few_ticks(ax, n: int = 5) -> None:
    from matplotlib.ticker import MaxNLocator

    ax.xaxis.set_major_locator(MaxNLocator(n))
    ax.yaxis.set_major_locator(MaxNLocator(n))


def gap_figures(rep: Report, d) -> None:
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    rep.heading("Held-out disagreement" + ("" if same_model(d) else ", before and after"))
    states = _states(d)
    fig, ax = plt.subplots(1, len(states), figsize=(5 * len(states), 3.4), squeeze=False)
    lim = np.percentile(np.abs(d.cv_before), 99.5)
    bins = np.linspace(-lim, lim, 60)
    x = np.linspace(-lim, lim, 200)
    s = d.noise_floor
    for a, (lab, data, _) in zip(ax[0], states):
        rms = float(np.sqrt(np.mean(np.square(data))))
        a.hist(np.clip(data.ravel(), -lim, lim), bins=bins, color=BLUE, alpha=0.8, density=True)
        a.plot(x, np.exp(-0.5 * (x / s) ** 2) / (s * np.sqrt(2 * np.pi)), "k--", lw=1,
               label=f"tracker noise ({s:.4f} mm)")
        a.set_title(f"{lab}: {rms:.4f} mm RMS", fontsize=10)
        a.set(xlabel="held-out residual, mm", ylabel="density, 1/mm")
        a.xaxis.set_major_locator(MaxNLocator(7))
        a.legend(fontsize=8)
    fig.tight_layout()
    rep.figure(fig, "Held-out residuals of every target coordinate of every pose (each pose predicted by the "
                    "model fitted without its fold), with the tracker-noise density")


def _apparent(d, lin) -> tuple[np.ndarray, np.ndarray]:
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


def _varies(v) -> bool:
    return v is not None and np.isfinite(v).all() and float(np.ptp(v)) > 0


def context_panels(d) -> tuple[list[tuple[str, np.ndarray, str]], list[str]]:
    """The contexts to plot against: (key, values (N,) or (N, 2), axis label), and the names of those left
    out because the campaign does not vary them."""
    from pmcal.twin.ocpm.effects import motor_torques

    meas = d.meas
    N = len(meas)
    t = np.asarray(meas.extra.get("effect_t_rel", np.arange(N)), float)
    panels = [("time", t, "time since first pose, h" if d.time_unit == "h" else "pose order (time unknown)")]
    missing = []
    if meas.approach is not None and np.any(meas.approach != 0):
        panels.append(("approach", meas.approach, "approach direction of the motor (-1, +1)"))
    else:
        missing.append("approach direction")
    panels.append(("motor", meas.m_cmd_deg, "motor angle, deg"))
    e, _ = errors_and_ratio(list(d.baseline.names), d.baseline.x)
    try:
        tau = motor_torques(e, meas.m_cmd_deg, meas.payload_kg, d.baseline.info["stiffness_ratio"])
    except (RuntimeError, ValueError):
        tau = None
    if tau is not None and np.isfinite(tau).all():
        panels.append(("torque", tau, "gravity torque at the motor, N m"))
    else:
        missing.append("gravity torque")
    if _varies(meas.temp_c):
        panels.append(("temperature", meas.temp_c, "temperature, degC"))
    else:
        missing.append("temperature")
    if _varies(meas.payload_kg):
        panels.append(("payload", meas.payload_kg, "payload, kg"))
    else:
        missing.append("payload")
    return panels, missing


def context_figures(rep: Report, d) -> None:
    import matplotlib.pyplot as plt

    rep.heading("Residual against context")
    rep.paragraph("Each pose's residual expressed as an apparent motor-angle error (what a motor offset would "
                  "have to be to explain it) and, against temperature, as an apparent uniform scale about O. "
                  "Backlash splits by approach, drift trends with time, eccentricity follows the motor angle, "
                  "compliance the gravity torque, thermal expansion the temperature.", "note")
    panels, missing = context_panels(d)
    if missing:
        which = missing[0] if len(missing) == 1 else f"{', '.join(missing[:-1])} or {missing[-1]}"
        rep.paragraph(f"No data: this campaign does not vary {which}, so "
                      f"{'that panel is' if len(missing) == 1 else 'those panels are'} left out "
                      "(docs/formats.md: the optional measurement columns).", "note")
    N = len(d.meas)
    cols = 3 if len(panels) > 4 else 2
    rows = (len(panels) + cols - 1) // cols
    for lab, _, lin in _states(d):
        motor, scale = _apparent(d, lin)
        fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 3.1 * rows + 0.4), squeeze=False)
        for a, (key, v, xlabel) in zip(axes.ravel(), panels):
            if key == "temperature":
                a.plot(v, scale, ".", color=GREEN)
                a.set_ylabel("apparent scale, ppm")
            else:
                for j, col in enumerate((BLUE, ORANGE)):
                    x = v[:, j] if np.ndim(v) == 2 else v
                    if key == "approach":
                        x = x + 0.08 * np.random.default_rng(j).standard_normal(N) + 0.25 * (j - 0.5)
                    a.plot(x, motor[:, j], ".", color=col, label=f"motor {j + 1}")
                a.set_ylabel("apparent motor error, deg")
            if key == "approach":
                a.set_xticks([-1, 1])
            else:
                _few_ticks(a)
            a.set_xlabel(xlabel)
            a.grid(alpha=0.3)
        axes.ravel()[0].legend(fontsize=8)
        for a in axes.ravel()[len(panels):]:
            a.axis("off")
        fig.suptitle(lab, fontsize=11)
        fig.tight_layout()
        rep.figure(fig, f"Residual against context ({lab})")


def added_variable_figures(rep: Report, d) -> None:
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

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
    fig, axes = plt.subplots(rows, cols, figsize=(12, 3.6 * rows), squeeze=False)
    for a, name in zip(axes.ravel(), names):
        x, y = (np.asarray(v, float) for v in d.added_variable[name])
        a.plot(x, y, ".", ms=2, alpha=0.35, color="#718096")
        if np.ptp(x) > 0:
            edges = np.quantile(x, np.linspace(0, 1, 16))
            idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, 14)
            xm = np.array([x[idx == b].mean() if np.any(idx == b) else np.nan for b in range(15)])
            ym = np.array([y[idx == b].mean() if np.any(idx == b) else np.nan for b in range(15)])
            a.plot(xm, ym, "-o", color="#c53030", ms=3)
            lim = np.max(np.abs(x))
            a.plot([-lim, lim], [-lim, lim], "k:", lw=1)
        cand = d.candidates.get(name)
        a.set_title(f"{name}\n({cand.verdict if cand is not None else '–'})", fontsize=9)
        a.set_xlabel("projected signature, mm")
        a.set_ylabel("residual without it, mm")
        a.ticklabel_format(style="plain", useOffset=False)
        a.xaxis.set_major_locator(MaxNLocator(4, symmetric=True))
        a.yaxis.set_major_locator(MaxNLocator(5))
        a.tick_params(labelsize=8)
        a.grid(alpha=0.3)
    for a in axes.ravel()[len(names):]:
        a.axis("off")
    fig.tight_layout()
    rep.figure(fig, "Added-variable plots at the final model")


def arrow_figures(rep: Report, d) -> None:
    import matplotlib.pyplot as plt

    meas = d.meas
    N = len(meas)
    _, R, _ = meas.poses()
    theta = np.rad2deg(np.arccos(np.clip(R[:, 2, 2], -1, 1)))
    phi = np.arctan2(R[:, 1, 2], R[:, 0, 2])
    x, y = theta * np.cos(phi), theta * np.sin(phi)
    rep.heading("Per-pose residuals")
    states = _states(d)
    res = [(lab, (lin.r * lin.sigma).reshape(N, -1, 3).mean(1)) for lab, _, lin in states]
    scale = max(np.percentile(np.linalg.norm(res[0][1][:, :2], axis=1), 95), 1e-9) / 8.0
    zmax = max(float(np.abs(res[0][1][:, 2]).max()), 1e-9)
    fig, ax = plt.subplots(1, len(res), figsize=(5.6 * len(res) + 1.4, 5.2), squeeze=False,
                           layout="constrained")
    q = None
    for a, (lab, r) in zip(ax[0], res):
        q = a.quiver(x, y, r[:, 0], r[:, 1], np.abs(r[:, 2]), angles="xy", scale_units="xy", scale=scale,
                     cmap="viridis", width=0.004, clim=(0, zmax))
        a.set_aspect("equal")
        a.set(xlabel="tilt x: theta cos(phi), deg", ylabel="tilt y: theta sin(phi), deg", title=lab)
        a.grid(alpha=0.3)
    fig.colorbar(q, ax=ax[0].tolist(), shrink=0.8, pad=0.03).set_label("|z| residual, mm", labelpad=8)
    rep.figure(fig, f"Mean residual of the targets of every pose (x, y as arrows, |z| as colour; arrow scale: "
                    f"{scale:.2g} mm per deg of the plot), placed at the pose's platform normal")
