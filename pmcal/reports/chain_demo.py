"""The HTML report of a machine folder's demo (:class:`pmcal.studies.chain_demo.ChainDemo`): what was
measured, what identification found and could not see, and what compensation gained on the true machine.
Units: mm and degrees."""

from __future__ import annotations

import numpy as np

from pmcal.mechanism.task_space import POSITION, error_families, rms
from pmcal.reports.html import Report, matplotlib_agg
from pmcal.twin.render import RenderUnavailable, render_machine_png, visible_moving_geoms

#: base errors listed in the report's table (largest identified first)
TABLE_ROWS = 20


def band_sentence(s: dict, name: str, unit: str) -> str:
    """The end of the compensation sentence: the band 90 % of campaigns like this one end in, and how many
    error directions carry the prediction (:meth:`pmcal.studies.chain_demo.ChainDemo.summary`)."""
    band = s.get(f"{name}_predicted_band_{unit}")
    if not band:
        return "."
    nu = s[f"{name}_predicted_directions"]
    few = (" (few directions carry it, so one campaign may well end near either edge)" if nu < 3 else "")
    return (f"; 90 % of campaigns like this one end between {band[0]:.4f} and {band[1]:.4f} {unit} RMS, "
            f"about {nu:.1f} independent error directions carrying the prediction{few}.")


def chain_demo_report(demo) -> Report:
    """The self-contained report of ``demo``."""
    matplotlib_agg()
    import matplotlib.pyplot as plt

    s = demo.summary()
    m, r = demo.machine, demo.result
    rep = Report(f"pmcal demo: {m.name}",
                 f"{m.spec.title or m.name}: the whole job on the machine folder's digital twin (seed {demo.seed})")
    fam = error_families(demo.coordinates)
    ok = all(s[f"{n}_rms_after_{u}"] < s[f"{n}_rms_before_{u}"] for n, u, _, _ in fam)
    rep.card("What the demo did", [
        f"A virtual machine with random geometric errors of the sizes machine.toml gives ({len(r.params)} errors), "
        f"measured at {s['campaign_poses']} poses planned D-optimally (uncertainties {s['plan_gain']:.2f}x smaller "
        "than as many random poses), tracker noise "
        f"{r.sigma_mm:g} mm.",
        f"Identification: {s['base_errors']} identifiable combinations (base set); residual {r.residual_rms_mm:.4f} mm "
        f"RMS, chi2/dof {r.chi2_per_dof:.2f} (1 = the model explains the data down to the tracker noise).",
        *(f"Compensation at {s['held_out_targets']} held-out targets: {n} error of the true machine "
          f"{s[f'{n}_rms_before_{u}']:.4f} {u} RMS (max {s[f'{n}_max_before_{u}']:.4f}) with the nominal inverse "
          f"kinematics, {s[f'{n}_rms_after_{u}']:.4f} {u} RMS (max {s[f'{n}_max_after_{u}']:.4f}) compensated; "
          f"the identification predicts {s[f'{n}_rms_predicted_{u}']:.4f} {u} RMS (the posterior over every error, "
          "propagated to the task)" + band_sentence(s, n, u) for n, u, _, _ in fam)],
        css="ok" if ok else "bad")
    warnings = demo.warnings(s)
    if warnings:
        rep.card("What to know", warnings, css="warn")
    try:
        png = render_machine_png(m.spec, m.twin.solve(m.twin.home_commands[None])[0], 800, 500)
        drawn = "scene.xml" if (m.spec.folder / "scene.xml").is_file() else m.spec.model_path.name
        if not visible_moving_geoms(m.twin.model):
            drawn += "; the model has no visible geometry: its kinematic skeleton and sites"
        rep.image_png(png, f"{m.name} at its home configuration ({drawn})")
    except (RenderUnavailable, ValueError) as exc:
        rep.paragraph(f"No picture: {exc}", "note")

    rep.heading("Compensation on held-out targets")
    coords = demo.coordinates
    rows = [[c, rms(demo.error_nominal[:, i]), rms(demo.error_compensated[:, i]), rms(demo.predicted[:, i])]
            for i, c in enumerate(coords)]
    rep.table(["task coordinate", "RMS nominal IK", "RMS compensated", "RMS predicted"], rows,
              caption="error of the true machine per task coordinate (mm or deg)")
    name, unit, _, size = fam[0]                 # position (mm) if the task has any, else orientation (deg)
    before, after = size(demo.error_nominal, coords), size(demo.error_compensated, coords)
    pos = [i for i, c in enumerate(coords) if c in POSITION]
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.6))
    bins = np.linspace(0.0, max(before.max(), after.max()) * 1.05 + 1e-12, 30)
    ax[0].hist(before, bins=bins, alpha=0.6, label="nominal IK")
    ax[0].hist(after, bins=bins, alpha=0.8, label="compensated")
    ax[0].set_xlabel(f"{name} error of the task site, {unit}")
    ax[0].set_ylabel("targets")
    ax[0].legend()
    if len(pos) >= 2:
        sc = ax[1].scatter(demo.task[:, pos[0]], demo.task[:, pos[1]], c=after, cmap="viridis", s=28)
        fig.colorbar(sc, ax=ax[1], label=f"compensated {name} error, {unit}")
        ax[1].set_xlabel(coords[pos[0]])
        ax[1].set_ylabel(coords[pos[1]])
        ax[1].set_title("held-out targets")
    else:
        ax[1].plot(after, "o", ms=3)
        ax[1].set_xlabel("target")
        ax[1].set_ylabel(f"compensated {name} error, {unit}")
    rep.figure(fig, f"Left: the task site's {name} error at each held-out target, driven by the nominal inverse "
                    "kinematics and by the compensated commands. Right: where the compensated error lies.")

    rep.heading("Compensation table for the PLC")
    if demo.table is None:
        rep.paragraph(demo.table_note, "note")
    else:
        t = s["table"]
        kind = ("corrections to the controller's own nominal inverse kinematics" if t["reference"] == "controller"
                else "absolute motor commands")
        rep.paragraph(f"table.json: {', '.join(t['axes'])}, {kind}. On the {t['targets_inside']} held-out targets "
                      f"inside its grid, the controller's nominal IK plus the PLC's interpolated correction puts the "
                      "true machine " + ", ".join(f"{t[f'{n}_rms_{u}']:.4f} {u} RMS (max {t[f'{n}_max_{u}']:.4f})"
                                                  for n, u, _, _ in fam)
                      + " from the target; the identified machine's exact IK "
                      + ", ".join(f"{s[f'{n}_rms_after_{u}']:.4f} {u} RMS" for n, u, _, _ in fam)
                      + " over all targets. Push it with pmcal push table.json --ads|--modbus ADDR.")
    rep.heading("Identification")
    res = np.linalg.norm(demo.meas.targets - m.twin.targets(demo.meas.commands, r.params), axis=2)
    fig, ax = plt.subplots(figsize=(10, 3.0))
    for k in range(res.shape[1]):
        ax.plot(np.arange(1, len(res) + 1), res[:, k], "o-", ms=3, lw=0.8, label=f"t{k + 1}")
    ax.axhline(np.sqrt(3.0) * r.sigma_mm, color="k", ls="--", lw=0.8, label="tracker noise (3-D)")
    ax.set_xlabel("pose (driving order)")
    ax.set_ylabel("residual, mm")
    ax.legend(ncol=4, fontsize=8)
    rep.figure(fig, "Distance between each measured nest and where the identified model puts it: noise, no "
                    "structure, when the geometric model holds.")
    truth = r.basis.combination_values(demo.truth)
    order = np.argsort(-np.abs(r.x))[:TABLE_ROWS]
    std = np.sqrt(np.diag(r.covariance))
    rep.table(["base error", "what it estimates", "unit", "identified", "+- 1 sigma", "true (combination)", "z"],
              [[r.base[i], r.combinations.get(r.base[i], ""), r.units[i], float(r.x[i]), float(std[i]),
                float(truth[i]), float((r.x[i] - truth[i]) / std[i])] for i in order],
              caption=f"the {len(order)} largest of {len(r.base)} identified base errors; z = (identified - true) / "
                      "sigma, about N(0, 1)", left_cols=3)
    if r.unidentifiable:
        rep.paragraph(f"Not separately identifiable ({len(r.unidentifiable)}): "
                      + "; ".join(r.unidentifiable[:12]) + (" ..." if len(r.unidentifiable) > 12 else ""), "note")
    rep.heading("Files")
    rep.table(["file", "what"], [
        ["plan.csv", "the planned poses (twin plan)"], ["measurements.csv", "the campaign (twin measure --plan)"],
        ["params.json", "identified errors, covariance, base set (identify)"],
        ["targets.csv", "held-out targets"], ["setpoints.csv", "their compensated commands (compensate)"],
        ["table.json, table.csv", "the compensation table for the PLC (compensate --table), when there is one"],
        ["summary.json", "the figures above"]], left_cols=2)
    rep.paragraph(f"Times: " + ", ".join(f"{k} {v:.1f} s" for k, v in s["timings_s"].items()), "note")
    return rep
