"""``pmcal --machine planar_2dof demo``: the paper's simulation study (Mei et al. 2017, section 6) on the
MuJoCo twin, side by side with the paper's Tables 3-6 and Fig. 8-9, and this project's improvement.

Writes ``<out>/report.html`` (self-contained), ``<out>/results.json`` and example files (a measurement CSV
of group 1 and the parameters identified from it). Units: mm and degrees.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

from pmcal import progress
from pmcal.errors import InputError

DEFAULT_RUNS = 60


#: display names of the settings (the keys of results.json stay "seed", "paper_scale_only", "ours")
LABELS = {"seed": "paper (eq. 34-35 noise)", "paper_scale_only": "paper, scale noise only", "ours": "pmcal"}

def _fig8(ns, k1, km, paper_fig8):
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6.4, 3.6))
    ax.plot(ns, k1, "o-", label="κ1 (first identification)")
    ax.plot(ns, km, "s--", label="κm (MAEMM-corrected, eq. 30)")
    ax.plot([paper_fig8["n"]] * 2, [paper_fig8["kappa1"], paper_fig8["kappam"]], "k*", ms=12,
            label="paper Fig. 8 at n = 3")
    ax.set_xlabel("n (positions per boundary, K = 2n; odd n as in the paper)")
    ax.set_ylabel("condition number of G")
    ax.grid(alpha=0.3)
    ax.legend()
    return fig


def _fig_positions(machine, paper_pos, ours_pos):
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle
    ws, reg = machine.workspace, machine.design.region
    fig, ax = plt.subplots(figsize=(8.4, 4.6))
    ax.add_patch(Rectangle((reg.x[0], reg.y[0]), reg.x[1] - reg.x[0], reg.y[1] - reg.y[0], fill=False,
                           ls=":", color="gray", label="calibration region (machine.toml [design])"))
    ax.add_patch(Rectangle((-ws.b / 2, ws.y_lower), ws.b, ws.h, alpha=0.2, color="tab:blue", label="workspace W"))
    ax.plot(*paper_pos.T, "o-", color="tab:blue", label="paper positions (Fig. 7, n = 3)")
    ax.plot(*ours_pos.T, "s-", color="tab:red", label="noise-optimal positions")
    g = machine.geometry
    ax.plot(*g.e.T, "k^", label="A1, A2")
    ax.plot(*(g.c), "kx", label="O1")
    ax.set_aspect("equal")
    ax.set_xlabel("x, mm")
    ax.set_ylabel("y, mm")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0)
    fig.tight_layout()
    return fig


def _fig9(fig9, groups):
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(2, 3, figsize=(11, 6), sharex=True)
    styles = {"seed": ("tab:blue", "paper, eq. 34-35"), "paper_scale_only": ("tab:green", "paper, scale only"),
              "ours": ("tab:red", "pmcal")}
    for ax, grp in zip(axes.ravel(), groups):
        for name, (col, lab) in styles.items():
            dev = fig9[grp][name]
            m = np.arange(1, len(dev) + 1)
            ax.plot(m, dev[:, 0], "-", color=col, label=f"{lab}: Δθ1")
            ax.plot(m, dev[:, 1], "--", color=col, label=f"{lab}: Δθ2")
        ax.axhspan(-0.1, 0.1, color="gray", alpha=0.12)
        ax.set_title(grp)
        ax.grid(alpha=0.3)
    for ax in axes[1]:
        ax.set_xlabel("m (compensation number)")
    for ax in axes[:, 0]:
        ax.set_ylabel("compensation − set value, deg")
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=3, fontsize=8)
    fig.tight_layout(rect=(0, 0.1, 1, 1))
    return fig


def _fig_delta(studies, groups, names):
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(9, 3.8))
    cols = {"seed": "tab:blue", "paper_scale_only": "tab:green", "ours": "tab:red"}
    for j, name in enumerate(names):
        data = [np.max(studies[g][name].delta_deg, axis=1) for g in groups]
        pos = np.arange(len(groups)) * (len(names) + 1) + j
        bp = ax.boxplot(data, positions=pos, widths=0.8, patch_artist=True, showfliers=False)
        for b in bp["boxes"]:
            b.set_facecolor(cols[name])
            b.set_alpha(0.6)
        ax.plot([], [], color=cols[name], lw=8, alpha=0.6, label=LABELS[name])
    ax.set_yscale("log")
    ax.axhline(0.04, color="k", ls="--", lw=1, label="paper Table 3 (≈0.04°)")
    ax.axhline(0.02, color="k", ls=":", lw=1, label="goal 0.02°")
    ax.set_xticks(np.arange(len(groups)) * (len(names) + 1) + 1, groups)
    ax.set_ylabel("max(δ1, δ2), deg")
    ax.set_xlabel("error group (paper Table 3)")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))     # outside: no box hidden
    ax.grid(alpha=0.3, which="both")
    return fig


def demo(args) -> int:
    from pmcal.calib.planar.design import boundary_positions, choose_n, condition_study, optimal_positions
    from pmcal.calib.planar.identification import identification_matrix, identify
    from pmcal.mechanism.planar.kinematics import actual_position
    from pmcal.fileio import atomic_directory
    from pmcal.fileio import write_json
    from pmcal.planar.io import params_document, write_measurements
    from pmcal.reports.html import matplotlib_agg
    from pmcal.twin.planar.config import default_machine
    from pmcal.apps.planar.study import GROUPS, PAPER, evaluate_at, run_study, settings
    from pmcal.twin.planar.twin import PlanarTwin, commands_for, measure

    runs = int(getattr(args, "runs", None) or DEFAULT_RUNS)
    seed = int(getattr(args, "seed", 1))
    draw = bool(getattr(args, "picture", True))
    out = Path(getattr(args, "out", "pmcal-demo"))
    matplotlib_agg()
    t0 = time.perf_counter()
    machine = default_machine()
    g, ws, cal = machine.geometry, machine.workspace, machine.calibration
    max_iter = int(getattr(args, "max_iterations", None) or cal.max_iterations)
    drM_set = machine.preset("group1").drM

    with progress.progress(total=6 * 3 + 8, desc="planar demo", unit="step") as bar:
        # Fig. 8 and eq. 31
        ns = np.arange(3, 22, 2)
        k1, km = condition_study(g, ws, ns, drM_set)
        n = choose_n(g, ws, cal.eps0, drM_set)
        paper_pos = boundary_positions(ws, n)
        bar.update(1)
        ours_pos = optimal_positions(g, machine.design.region, machine.design.positions, machine.noise,
                                     step=machine.design.grid_step)
        bar.update(1)
        # identifiability (section 4)
        rank_s = int(np.linalg.matrix_rank(identification_matrix(g, paper_pos)))
        r14 = boundary_positions(ws, 7)
        Gf = identification_matrix(g, r14, "full")
        sv_full = np.linalg.svd(Gf, compute_uv=False)
        rank_f = int(np.linalg.matrix_rank(Gf))
        # the twin against the closed forms
        tw1 = PlanarTwin(machine.preset("group1"), machine)
        poses = tw1.assemble(commands_for(tw1, paper_pos))
        fk_diff = float(np.max(np.abs(poses.r - actual_position(g, tw1.errors, commands_for(tw1, paper_pos)))))
        bar.update(1)

        sets = settings(machine, paper_pos, ours_pos)
        studies: dict[str, dict] = {}
        dpmax_paperpos: dict[str, dict] = {}
        fig9: dict[str, dict] = {}
        for gi, grp in enumerate(GROUPS):
            err = machine.preset(grp)
            tw = tw1 if grp == "group1" else PlanarTwin(err, machine)
            studies[grp], dpmax_paperpos[grp], fig9[grp] = {}, {}, {}
            for si, s in enumerate(sets):
                # Runs stop at convergence (eq. 32), except the first, which goes on to max_iter for Fig. 9.
                res = run_study(err, s.positions, s.noise, runs, seed=seed * 1000 + 10 * gi + si, method=s.method,
                                mu0=cal.mu0, max_iter=max_iter, stop=np.arange(runs) > 0, twin=tw)
                studies[grp][s.name] = res
                dpmax_paperpos[grp][s.name] = evaluate_at(tw, paper_pos, res.comp_deg)
                fig9[grp][s.name] = np.rad2deg(res.runs[0].history()["comp"]) - np.rad2deg(err.dtheta)
                bar.update(1)
        dpmax_before = {grp: float(evaluate_at(PlanarTwin(machine.preset(grp), machine), paper_pos,
                                               np.zeros((1, 2)))[0]) for grp in GROUPS}
        bar.update(1)

        # eq. 25 (full model) against eq. 28 (simplified) on one campaign of K = 14, group 1
        rng = np.random.default_rng(seed)
        full_cmp = []
        for label, noise in (("noise-free", machine.noise.scaled(0.0)), ("noise eq. 34-35", machine.noise)):
            camp = measure(tw1, commands_for(tw1, r14), noise, rng)
            for model, method in (("simplified", "tsvd"), ("full", "ls"), ("full", "tsvd")):
                res = identify(g, r14, camp.readings[0], model=model, method=method)
                d = res.as_dict()
                full_cmp.append([label, f"{model} / {method}", res.info["rank"], res.info["cond"],
                                 math.degrees(d["dtheta1"]), math.degrees(d["dtheta2"]), d["drMx"], d["drMy"]])
        bar.update(1)

        with atomic_directory(out) as tmp:
            # example files: a group-1 campaign at the paper's positions and its identification
            camp = measure(tw1, commands_for(tw1, paper_pos), machine.noise, np.random.default_rng(seed))
            write_measurements(tmp / "measurements_group1.csv", camp.theta_cmd[0], camp.readings[0],
                               targets=paper_pos, comments=[
                                   "pmcal demo: machine planar_2dof, errors: preset group1 (paper Table 2), "
                                   f"seed {seed}", "units: mm, deg; seed frame O-xy (y up)"])
            ex = identify(g, paper_pos, camp.readings[0], method=cal.method, noise=machine.noise)
            write_json(tmp / "params_group1.json", params_document(ex, {"source": "measurements_group1.csv"}))
            bar.update(1)
            picture = "not drawn"
            try:
                if draw:
                    from pmcal.twin.planar.twin import render_png
                    picture = render_png(tw1, width=720, height=540)
            except Exception as exc:  # rendering is optional (no OpenGL): the report says so
                picture = f"{exc.__class__.__name__}: {exc}"
            bar.update(1)

            results = _results(machine, studies, dpmax_paperpos, dpmax_before, PAPER, ns, k1, km, n, rank_s,
                               rank_f, sv_full, fk_diff, full_cmp, runs, seed, paper_pos, ours_pos, sets)
            results["elapsed_s"] = time.perf_counter() - t0
            write_json(tmp / "results.json", results)
            rep = _report(machine, results, studies, fig9, dpmax_paperpos, PAPER, ns, k1, km, paper_pos, ours_pos,
                          picture, sets, full_cmp)
            rep.write(tmp / "report.html")
            bar.update(2)
    t = time.perf_counter() - t0
    s = results["groups"]
    worst = {label: max(max(s[grp][name]["delta_deg_median"]) for grp in GROUPS) for name, label in
             (("seed", "paper"), ("paper_scale_only", "paper, scale only"), ("ours", "pmcal"))}
    print(f"planar_2dof demo: {runs} runs per group and setting, {t:.1f} s -> {out}/report.html; "
          "worst-group median zero-offset error: " + ", ".join(f"{k} {v:.4f} deg" for k, v in worst.items()),
          flush=True)
    return 0


def _results(machine, studies, dpmax_paperpos, dpmax_before, PAPER, ns, k1, km, n, rank_s, rank_f, sv_full,
             fk_diff, full_cmp, runs, seed, paper_pos, ours_pos, sets) -> dict:
    groups = {}
    for grp, per in studies.items():
        groups[grp] = {}
        for name, res in per.items():
            d = res.summary()
            d["dpmax_paper_positions_before_mm"] = dpmax_before[grp]
            d["dpmax_paper_positions_after_median_mm"] = float(np.median(dpmax_paperpos[grp][name]))
            groups[grp][name] = d
    return {
        "mechanism": "planar_2dof", "runs_per_setting": runs, "seed": seed,
        "noise": {"scale_sigma_mm": machine.noise.scale, "servo_sigma_deg": math.degrees(machine.noise.servo)},
        "settings": {s.name: {"label": s.label, "method": s.method, "positions_mm": s.positions,
                              "scale_sigma_mm": s.noise.scale, "servo_sigma_deg": math.degrees(s.noise.servo)}
                     for s in sets},
        "condition": {"n": ns, "kappa1": k1, "kappam": km, "n_chosen": n,
                      "paper_fig8": PAPER["fig8"]},
        "rank": {"simplified_K6": rank_s, "full_K14": rank_f, "full_singular_values": sv_full,
                 "paper_claim": {"simplified": 4, "full": 12}},
        "twin_vs_closed_form_max_mm": fk_diff,
        "full_model_comparison": [dict(zip(["noise", "model/method", "rank", "cond", "dtheta1_deg",
                                            "dtheta2_deg", "drMx_mm", "drMy_mm"], row)) for row in full_cmp],
        "groups": groups,
        "paper_tables": PAPER,
    }


def _report(machine, results, studies, fig9, dpmax_paperpos, PAPER, ns, k1, km, paper_pos, ours_pos, picture,
            sets, full_cmp):
    from pmcal.reports.html import Report
    from pmcal.apps.planar.study import GROUPS

    R = Report("Planar 2-DOF robot: zero-offset calibration with the measuring mechanism",
               subtitle="Reproduction of Mei et al. 2017 (the paper) on the MuJoCo twin, and an improvement. "
                        f"{results['runs_per_setting']} noise realisations per group and setting.")
    nz = results["noise"]
    med = lambda grp, name, key: results["groups"][grp][name][key]  # noqa: E731
    worst = {name: max(max(med(g, name, "delta_deg_median")) for g in GROUPS) for name in
             ("seed", "paper_scale_only", "ours")}
    R.card("Findings: the paper's method (6 positions, TSVD, eq. 29) and pmcal's (noise-optimal positions "
           "+ GLS)", [
        f"Model: κ1 = {k1[0]:.2f} at n = 3 (paper 475.34); Δp0 and Δp_max before calibration equal the paper's "
        f"Tables 3-4 within 0.002 mm. The twin matches the closed-form kinematics to "
        f"{results['twin_vs_closed_form_max_mm']:.1e} mm.",
        f"Paper method under the paper's own noise (eq. 34-35: σ_scale = {nz['scale_sigma_mm']:.6f} mm, "
        f"ξ = {nz['servo_sigma_deg']:.4f}°): median zero-offset error up to {worst['seed']:.3f}° — ten times the "
        "paper's 0.04°. This is the noise floor of 6 positions inside W, not a defect of the solver "
        "(Cramér-Rao bound ≈ 0.52°).",
        f"With the servo noise switched off the same method gives {worst['paper_scale_only']:.3f}° (worst-group "
        "median): the paper's Table 3 is reproduced under that reading.",
        f"Noise-optimal positions in an enlarged calibration region + GLS: {worst['ours']:.4f}° (worst-group "
        "median) under the full noise of eq. 34-35.",
        f"Rank of the full model (eq. 24, K = 14): {results['rank']['full_K14']}, not 12 as the paper states: "
        "translating the base with O1, and turning the robot about O1, change no distance.",
    ], css="ok")
    if isinstance(picture, bytes):
        R.image_png(picture, "The twin at home P0 (MuJoCo, offscreen): limb 1 with proximal and distal "
                             "parallelograms, limb 2, measuring mechanism between O1 and O2.")
    else:
        R.paragraph(f"(No picture: {picture})", css="note")

    R.heading("Measurement positions and condition numbers (paper section 5, Fig. 7-8)")
    R.figure(_fig8(ns, k1, km, PAPER["fig8"]), "Fig. 8 reproduced: κ1 and κm of the simplified model vs n "
             "(κm with the mechanism corrected by ΔrM = (1, 0.5) mm).")
    R.table(["n", "κ1 ours", "κ1 paper", "κm ours", "κm paper", "|κ1-κm|/κ1"],
            [[3, k1[0], PAPER["fig8"]["kappa1"], km[0], PAPER["fig8"]["kappam"], abs(k1[0] - km[0]) / k1[0]]]
            + [[int(n), a, "", b, "", abs(a - b) / a] for n, a, b in zip(ns[1:], k1[1:], km[1:])])
    R.paragraph(f"Eq. 31 with ε0 = {machine.calibration.eps0} picks n = {results['condition']['n_chosen']} "
                "(K = 6). κm uses the correction λ − ΔrM of eq. 30 (the sign that follows from eq. 16-17; the "
                "other sign gives 478.4 > κ1). The paper's 472.54 is 0.04 % above ours (see docs/planar.md).",
                css="note")
    R.figure(_fig_positions(machine, paper_pos, ours_pos), "Paper positions (Fig. 7) and this project's "
             "noise-optimal positions (A-optimal for Δθ, GLS, scale range and transmission constraints).")

    R.heading("Table 3: zero offsets and Δp0 (paper vs this twin)")
    rows = []
    for grp in GROUPS:
        s3 = PAPER["table3"][grp]
        set_ = np.rad2deg(machine.preset(grp).dtheta)
        for i in range(2):
            rows.append([grp if i == 0 else "", f"Δθ{i + 1}", set_[i], s3[2 * i], s3[2 * i + 1],
                         med(grp, "seed", "delta_deg_median")[i], med(grp, "paper_scale_only", "delta_deg_median")[i],
                         med(grp, "ours", "delta_deg_median")[i],
                         s3[4] if i == 0 else "", med(grp, "seed", "dp0_before_mm") if i == 0 else "",
                         s3[5] if i == 0 else "",
                         med(grp, "seed", "dp0_after_median_mm") if i == 0 else "",
                         med(grp, "paper_scale_only", "dp0_after_median_mm") if i == 0 else "",
                         med(grp, "ours", "dp0_after_median_mm") if i == 0 else ""])
    R.table(["group", "", "set °", "paper comp. °", "paper δ °", "δ paper-method °", "δ scale-only °", "δ ours °",
             "Δp0 before paper", "Δp0 before ours", "Δp0 after paper", "after paper-method", "after scale-only",
             "after ours"], rows, left_cols=2,
            caption="δ: |compensation − set value|, median over the runs; Δp0 in mm (after: median).")

    R.heading("Table 4: Δp_max at the six paper positions, before and after (mm)")
    R.table(["group", "before paper", "before ours", "after paper", "after paper-method", "after scale-only",
             "after ours"],
            [[grp, PAPER["table4"][grp][0], results["groups"][grp]["seed"]["dpmax_paper_positions_before_mm"],
              PAPER["table4"][grp][1]] + [float(np.median(dpmax_paperpos[grp][n])) for n in
                                          ("seed", "paper_scale_only", "ours")] for grp in GROUPS])

    R.heading("Table 5: MAEMM identification error δM (mm) and Table 6: mean κ")
    R.table(["group", "δMx paper", "δMy paper", "δMx/δMy paper-method", "δMx/δMy scale-only", "δMx/δMy ours",
             "κ mean paper", "κ mean ours"],
            [[grp, PAPER["table5"][grp][0], PAPER["table5"][grp][1]]
             + ["{:.3f} / {:.3f}".format(*med(grp, n, "delta_M_median_mm")) for n in
                ("seed", "paper_scale_only", "ours")]
             + [PAPER["table6"][grp], med(grp, "seed", "cond_later_mean")] for grp in GROUPS],
            caption="δM: median over the runs. κ mean: identifications 2..m of the paper method (eq. 30).")

    R.heading("Fig. 9: robustness over m = 1..19 identifications")
    R.figure(_fig9(fig9, GROUPS), "Compensation value minus set value vs compensation number m, one run per "
             "group and setting (grey band ±0.1°).")
    R.figure(_fig_delta(studies, GROUPS, ["seed", "paper_scale_only", "ours"]),
             "Distribution of the larger zero-offset error per run, per group and setting.")
    R.table(["group", "setting", "δ median °", "δ RMS °", "δ p95 °", "m median", "converged"],
            [[grp, LABELS[s.name], max(med(grp, s.name, "delta_deg_median")), max(med(grp, s.name, "delta_deg_rms")),
              max(med(grp, s.name, "delta_deg_p95")), med(grp, s.name, "m_median"),
              med(grp, s.name, "converged_fraction")] for grp in GROUPS for s in sets], left_cols=2)

    R.heading("Full model (eq. 25) against the simplified model (eq. 28), group 1, K = 14")
    R.table(["noise", "model / method", "rank", "κ", "Δθ1 °", "Δθ2 °", "ΔrMx, mm", "ΔrMy, mm"], full_cmp, left_cols=2,
            caption="Set values: Δθ = (2, −1)°, ΔrM = (1, 0.5) mm. One identification (no compensation loop).")
    R.paragraph("G' has rank 9: two translations of the base together with O1, and a rotation of the robot "
                "about O1, leave every distance O1O2 unchanged, so eq. 25's normal matrix is singular and the "
                "common part of the zero offsets is not identifiable with the geometric errors free. The "
                "simplified model fixes that gauge by assuming the geometric errors are zero.", css="note")
    R.heading("Settings")
    R.table(["name", "what", "scale σ, mm", "servo ξ °"],
            [[LABELS[s.name], s.label, f"{s.noise.scale:.6f}", math.degrees(s.noise.servo)] for s in sets],
            left_cols=2)
    return R
