"""The demo's HTML report: figures and tables of a :class:`pmcal.studies.ocpm.demo.DemoStudy` (mm, degrees)."""

from __future__ import annotations

import numpy as np

from pmcal.calib.ocpm import paper_model as pm



def _paper(label: str) -> str:
    """Display name of a summary key: the source paper's method is "paper" (the keys keep "seed")."""
    return label.replace("seed", "paper", 1) if label.startswith("seed") else label

def _stats(a: np.ndarray) -> str:
    return f"mean {np.mean(np.abs(a)):.4f}, max {np.max(np.abs(a)):.4f}"


def _png(fig_pickle: bytes, dpi: int) -> bytes:
    """PNG of a pickled matplotlib figure, as :meth:`Report.figure` draws it (a worker-process entry point)."""
    import io
    import pickle

    from pmcal.reports.html import matplotlib_agg

    matplotlib_agg()
    fig = pickle.loads(fig_pickle)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
    return buf.getvalue()


def _parallel_figures(rep, pool):
    """Make ``rep.figure`` draw in ``pool`` (drawing is most of a report's time); returns a function that
    puts the finished PNGs in their places."""
    import pickle

    import matplotlib.pyplot as plt

    pending = []

    def figure(fig, caption: str = "", dpi: int = 110) -> None:
        data = pickle.dumps(fig)
        plt.close(fig)
        rep.parts.append("")
        pending.append((len(rep.parts) - 1, caption, pool.submit(_png, data, dpi)))

    def resolve() -> None:
        for i, caption, future in pending:
            rep.image_png(future.result(), caption)
            rep.parts[i] = rep.parts.pop()

    rep.figure = figure
    return resolve


def demo_report(st, pool=None):
    """The demo's self-contained HTML report; figures drawn in the process ``pool`` when given."""
    from pmcal.reports.html import Report, matplotlib_agg

    matplotlib_agg()
    import matplotlib.pyplot as plt

    from pmcal.mechanism.ocpm.params import PAPER_TABLE2_IDENTIFIED, describe, unit

    rep = Report("pmcal demo: calibration of the over-constrained 2-DoF PM",
                 "Digital twin with the paper's Table 2 errors (limbs 1 and 2), closure compliance, tracker "
                 f"noise {st.geom.sigma_mm} mm; {st.N_CAL} calibration poses, {st.N_TEST} held-out test poses, "
                 f"seed {st.seed}. Method: the paper (Sun et al. 2018), sections IV-VI.")
    resolve = _parallel_figures(rep, pool) if pool is not None else (lambda: None)
    b, a = st.before["pointing"], st.after["pointing"]
    rep.card("Result: the paper's HGA method (with the fitted position map) and the whole closed chain",
             [f"pointing error before: {_stats(b)} deg", f"after (paper HGA method): {_stats(a)} deg",
                        f"after (whole closed chain): {_stats(st.full_after)} deg",
                        f"improvement of the mean, paper HGA method: {100 * (1 - a.mean() / b.mean()):.1f} % (paper, experiment: "
                        "93.96 % in theta, 90.38 % in phi)",
                        f"HGA identification of both limbs: {st.cal.wall_time:.2f} s; whole demo "
                        f"{st.timings.get('total', 0):.0f} s"], css="ok")
    rep.heading("The machine")
    if st.render_png:
        rep.image_png(st.render_png, "MuJoCo twin at phi = 45 deg, theta = 30 deg")
    else:
        rep.paragraph(st.render_note or "render unavailable", css="note")
    cl = st.closure
    rep.paragraph(f"Over-constraint: on the calibration poses the passive limbs' closures miss by up to "
                  f"{cl[:, 2:].max():.2f} mm (absorbed by compliance), the actuated ones by "
                  f"{cl[:, :2].max():.4f} mm: the paper's per-limb model is nearly exact for these data.")

    # ---- Table 2
    rep.heading("Identified vs predefined errors (paper Table 2)")
    std = st.cal.uncertainty()
    got = st.cal.params()
    rows = []
    for k in st.cal.names:
        v = got.get(k)
        rows.append([k, describe(k), unit(k), PAPER_TABLE2_IDENTIFIED.get(k, float("nan")), st.truth.get(k, 0.0),
                     float("nan") if v is None else v, float("nan") if std[k] is None else std[k],
                     "unidentifiable" if v is None else f"{(v - st.truth.get(k, 0.0)) / std[k]:+.2f}"])
    rep.table(["key", "meaning", "unit", "paper identified", "predefined", "pmcal HGA", "CRLB std",
               "deviation / std"], rows, left_cols=3,
              caption="Positions mm, angles deg. CRLB: Cramer-Rao standard deviation at 0.01 mm tracker noise.")

    # ---- Fig. 5
    rep.heading("Pointing before and after compensation (paper Fig. 5)")
    fig, ax = plt.subplots(1, 3, figsize=(13, 3.6), layout="constrained")
    idx = np.arange(1, st.N_TEST + 1)
    for k, (key, lab) in enumerate((("dtheta", "theta deviation, deg"), ("dphi", "phi deviation, deg"),
                                    ("pointing", "pointing error, deg"))):
        ax[k].plot(idx, st.before[key], "o-", label="before")
        ax[k].plot(idx, st.after[key], "s-", label="after (pmcal)")
        ax[k].set_xlabel("test point")
        ax[k].set_ylabel(lab)
        ax[k].set_title(lab.split(",")[0])
        ax[k].grid(alpha=.3)
    ax[0].legend()
    rep.figure(fig, "Tilt, azimuth and pointing deviations of the 24 test points")
    rep.table(["compensation", "mean pointing, deg", "max pointing, deg", "mean |dtheta|, deg", "mean |dphi|, deg"],
              [[k.replace("(seed)", "(paper)"), v["pointing"].mean(), v["pointing"].max(), np.abs(v["dtheta"]).mean(),
                np.abs(v["dphi"]).mean()]
               for k, v in st.variants.items()],
              caption="The paper's eq. 7 position limits compensation even with the true errors; the position "
                      "map fitted to the measured platform positions removes that limit.")

    # ---- whole chain
    rep.heading("Paper method vs whole closed chain")
    rows = []
    for case, d in st.fullchain.items():
        for m, v in d.items():
            if not m.startswith("_"):
                rows.append([case, _paper(m), v.mean(), v.max(), 100 * (1 - v.mean() / d["before"].mean())])
    rep.table(["machine", "compensation", "mean pointing, deg", "max pointing, deg", "improvement %"], rows,
              left_cols=2, caption="Same 24 calibration poses and 24 held-out test poses for every method. The "
              "whole-chain model (docs/fullchain.md) fits all four limbs, the SS limb and the closure stiffness "
              "ratio to the raw target coordinates; the tracker's own noise floor is ~0.006 deg.")
    fig, ax = plt.subplots(1, len(st.fullchain), figsize=(13, 3.8), sharey=True, layout="constrained")
    for a_, (case, d) in zip(np.atleast_1d(ax), st.fullchain.items()):
        for m, v in d.items():
            if not m.startswith("_"):
                a_.semilogy(idx, np.maximum(v, 1e-4), "o-", ms=3, label=_paper(m))
        a_.set_title(case, fontsize=9)
        a_.set_xlabel("test point")
        a_.grid(alpha=.3)
    np.atleast_1d(ax)[0].set_ylabel("pointing error, deg")
    np.atleast_1d(ax)[0].legend(fontsize=7)
    rep.figure(fig, "Held-out pointing errors: paper method and whole closed chain")
    doc = st.fullchain["Table 2, limbs 1-2"]["_calibration"].document
    rep.paragraph(f"Whole-chain fit (Table 2 machine): chi2/dof {doc['fit']['chi2_per_dof']:.3f}, effective "
                  f"parameters {doc['identifiability']['effective_parameters']:.1f} of 55, stiffness ratio "
                  f"{doc['stiffness_ratio']:.3g}, {doc['solver']['wall_time_s']:.2f} s; "
                  f"{len(doc['identifiability']['not_determined_by_campaign'])} parameters held by their priors "
                  "(not determined by this campaign). The compensation table below comes from this model.")

    _tracker_section(rep, st)

    # ---- Fig. 7-8
    rep.heading("Algorithm comparison (paper Fig. 7-8)")
    rows = []
    for m, d in st.methods.items():
        dev = np.array([d["dev"][k] for k in d["dev"]])
        ang = np.array([unit(k) == "deg" for k in d["dev"]])
        rows.append([m, d["wall"], d["n_eval"], d["chi_rms"], np.max(np.abs(dev[~ang])), np.max(np.abs(dev[ang])),
                     d["held_out"].mean()])
    rep.table(["method", "time, s", "evaluations", "residual rms, sigma", "max |pos. dev|, mm",
               "max |ang. dev|, deg", "held-out pointing, deg"], rows,
              caption="Both limbs, same 24 poses. Deviation: identified minus predefined. Residual 1 = noise level. "
                      "ga/pso/sa ran in two parallel worker processes (times inflated by sharing the CPU)"
                      + ("" if st.full else " with capped budgets ("
                         + ", ".join(f"{m}: {', '.join(f'{k} {v}' for k, v in o.items())}"
                                     for m, o in st.budgets.items())
                         + "; pmcal demo --full runs them to their own stopping rules)")
                      + "; clean timings: benchmarks/identify_bench.py.")
    keys = list(st.methods["hga"]["dev"])
    fig, ax = plt.subplots(2, 1, figsize=(13, 6.5), layout="constrained")
    width = 0.8 / len(st.methods)
    for i, (m, d) in enumerate(st.methods.items()):
        for row, is_ang in enumerate((False, True)):
            ks = [k for k in keys if (unit(k) == "deg") == is_ang]
            ax[row].bar(np.arange(len(ks)) + i * width, [d["dev"][k] for k in ks], width, label=m)
            ax[row].set_xticks(np.arange(len(ks)) + 0.4, ks, rotation=60, fontsize=7)
    ax[0].set_ylabel("position deviation, mm")
    ax[1].set_ylabel("orientation deviation, deg")
    ax[0].legend(ncol=7, fontsize=8)
    for x in ax:
        x.grid(alpha=.3)
    rep.figure(fig, "Deviation of the identified from the predefined errors per method")

    # ---- Fig. 6
    rep.heading("Regularisation (paper Fig. 6, eq. 18-20)")
    lams, res, sol, corner = st.lcurve
    fig, ax = plt.subplots(1, 2, figsize=(12, 3.8), layout="constrained")
    ax[0].loglog(res, sol, "-")
    k = int(np.argmin(np.abs(lams - corner)))
    ax[0].loglog(res[k], sol[k], "ro", label=f"corner, lambda = {corner:.3g}")
    ax[0].set_xlabel("residual norm |H x - dX| (whitened)")
    ax[0].set_ylabel("solution norm (box-scaled)")
    ax[0].legend()
    ax[0].set_title("L-curve")
    for name, d in st.regular.items():
        ax[1].plot(idx, d["held_out"]["pointing"], "o-", label=name)
    ax[1].plot(idx, b, "k:", label="before")
    ax[1].set_xlabel("test point")
    ax[1].set_ylabel("pointing error, deg")
    ax[1].legend(fontsize=8)
    rep.figure(fig, "Tikhonov / TSVD on the paper's linearised pose-error model vs HGA on the real IK model")
    rep.table(["method", "mean pointing, deg", "max pointing, deg", "lambda / rank"],
              [[n, d["held_out"]["pointing"].mean(), d["held_out"]["pointing"].max(),
                "" if d["res"] is None else (f"{d['res'].info['lambda']:.3g}" if "tikhonov" in n
                                             else str(d["res"].info["rank"]))] for n, d in st.regular.items()],
              caption=f"Condition number of the linear model (96 poses, column-normalised): {st.reg_cond:.3g} "
                      "(paper: 6.72e4).")

    # ---- identifiability
    rep.heading("Identifiability")
    lines = []
    for j in (1, 2):
        d, s = st.design[j], st.ident[j]
        lines.append(f"limb {j}: condition number {s.condition_number:.3g} at the solution "
                     f"({d.condition_number:.3g} on the nominal design); weak (CRLB > box): "
                     f"{', '.join(s.weak) or 'none'}")
    for k in st.cal.unidentifiable:
        lines.append(f"{k} is unidentifiable: {pm.explain(k)}. Held at 0.")
    rep.card("Identification Jacobian (whitened, column-normalised)", lines, css="warn")
    fig, ax = plt.subplots(1, 3, figsize=(15, 4.6), layout="constrained")
    for j in (1, 2):
        ax[0].semilogy(st.ident[j].singular_values, "o-", label=f"limb {j}")
    ax[0].set_title("singular values")
    ax[0].set_xlabel("index")
    ax[0].set_ylabel("singular value (whitened, column-normalised)")
    ax[0].legend()
    corr = st.ident[1].correlation
    im = ax[1].imshow(corr, vmin=-1, vmax=1, cmap="RdBu_r")
    ax[1].set_xticks(range(len(st.ident[1].names)), st.ident[1].names, rotation=90, fontsize=7)
    ax[1].set_yticks(range(len(st.ident[1].names)), st.ident[1].names, fontsize=7)
    ax[1].set_title("correlations, limb 1")
    fig.colorbar(im, ax=ax[1], shrink=0.8, label="correlation coefficient")
    ps = st.pose_sel
    n = ps["names"]
    to_deg = np.array([np.rad2deg(1.0) if unit(k) == "deg" else 1.0 for k in n])   # CRLBs: mm and rad
    ax[2].semilogy(range(len(n)), ps["random (median of 200)"]["crlb"] * to_deg, "o", label="random 24")
    ax[2].semilogy(range(len(n)), ps["D-optimal (identification)"]["crlb"] * to_deg, "s", label="D-optimal 24")
    ax[2].set_xticks(range(len(n)), n, rotation=90, fontsize=7)
    ax[2].set_title("Cramér-Rao standard deviation")
    ax[2].set_ylabel("CRLB std: mm (positions), deg (angles)")
    ax[2].legend()
    rep.figure(fig, "Singular values, correlations, and Cramer-Rao bounds for random vs D-optimal poses")
    rep.heading("Pose selection (Mei et al. 2017 section 5, generalised)")
    is_mm = np.array([unit(k) == "mm" for k in n])
    mm_dev = lambda dev: max(abs(v) for k, v in dev.items() if unit(k) == "mm")  # noqa: E731
    rows = [["random (median of 200 draws)", ps["random (median of 200)"]["cond"],
             np.max(ps["random (median of 200)"]["crlb"][is_mm]), "", ""],
            ["the demo's campaign (spread, random jitter)", st.ident[1].condition_number, "",
             st.after["pointing"].mean(), mm_dev(st.methods["hga"]["dev"])]]
    for label in ("D-optimal (identification)", "D-optimal (identification + position map)"):
        d = ps[label]
        rows.append([label, d["cond"], np.max(d["crlb"][is_mm]), d["held_out"].mean(), mm_dev(d["dev"])])
    rep.table(["24 poses", "condition number", "max CRLB of a position, mm", "held-out pointing, deg",
               "max |pos. dev|, mm"], rows,
              caption="Chosen from 600 candidates over theta <= 60 deg on the nominal design (both limbs). "
                      "Identification-only D-optimal poses cluster at the workspace edge: best CRLBs, but the "
                      "position map then extrapolates; the joint criterion keeps both.")

    # ---- table
    rep.heading("Compensation table")
    t = st.table
    rep.paragraph(f"comp_table.json / comp_table.csv: {t.n_phi} x {t.n_theta} nodes over phi "
                  f"{t.phi_min_deg:g}..{t.phi_max_deg:g} deg and theta {t.theta_min_deg:g}..{t.theta_max_deg:g} deg, "
                  f"absolute motor commands in deg, version {t.version}, CRC-32 0x{t.crc32():08X}.")
    rep.table(["step", "seconds"], [[k, v] for k, v in st.timings.items()])
    resolve()
    return rep


def _tracker_section(rep, st) -> None:
    """The tracker-frame run: registration, nests, blocked targets, the named outlier (docs/tracker_frame.md)."""
    sm, doc = st.tracker_summary(), st.tracker["document"]
    base = st.fullchain["Table 2, limbs 1-2"]["whole closed chain"]
    rep.heading("Tracker in its own frame: registration, nests, blocked targets, an outlier")
    rej = ", ".join(f"row {r} target T{k}" for r, k in sm["rejected"]) or "none"
    planted = ", ".join(f"row {r} target T{k}" for r, k in sm["outliers_planted"]) or "none"
    rep.card(f"{st.N_CAL} poses designed for the tracker frame (pmcal twin plan --frame tracker: D-optimal, "
             "to 80 deg), measured by a tracker 1-3 m away, any yaw; pmcal identify --frame tracker", [
        f"pointing error after (held-out, in the base frame of the motor axes): {_stats(st.tracker['pointing'])} "
        f"deg; the demo's {st.N_CAL} poses to {st.theta_max:g} deg measured in the twin's base frame: {_stats(base)} deg (Table 2 tilts the motor "
        f"axes {sm['motor_axes_vs_twin_frame_deg']:.3f} deg from it: from tracker data the base frame is the "
        "motor axes, docs/tracker_frame.md)",
        f"registration: rotation error {sm['registration_rotation_error_deg']:.4f} deg (reported std "
        f"{sm['registration_rotation_std_deg']:.4f} deg), translation error "
        f"{sm['registration_translation_error_mm']:.3f} mm (std {sm['registration_translation_std_mm']:.3f} mm)",
        f"gross outlier planted (2 mm): {planted}; rejected by the robust fit: {rej}"
        + ("" if sm["outliers_named"] else " (NOT all named)"),
        f"blocked targets in rows: {', '.join(map(str, sm['blocked_rows'])) or 'none'}; nests 0.3 mm off the "
        f"drawing, identified (params_tracker.json); tracker run (design, campaign, fit) {sm['wall_time_s']:.1f} s"])
    off = np.array(list(doc["nests"]["offsets_mm"].values()))
    std = np.array(list(doc["nests"]["std_mm"].values()))
    true = st.tracker["nest_offsets"]
    rep.table(["nest", "identified x, y, z (mm)", "true x, y, z (mm)", "std x, y, z (mm)"],
              [[f"T{k + 1}", ", ".join(f"{v:+.4f}" for v in off[k]), ", ".join(f"{v:+.4f}" for v in true[k]),
                ", ".join(f"{v:.4f}" for v in std[k])] for k in range(len(off))], left_cols=4,
              caption="Nest offsets from the drawing in platform coordinates (shape part: the rigid part is "
                      "platform geometry, docs/tracker_frame.md). The base frame is the motor axes; from "
                      "tracker data it is known only to the registration's rotation std, which is most of the "
                      "difference to the base-frame fit. The designed campaign fixes the frame about three "
                      "times better than poses spread evenly to 60 deg (benchmarks/tracker_bench.py).")
