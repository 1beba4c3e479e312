"""The HTML report of ``pmcal history DIR --report FILE.html``: the calibrations of a machine, what moved
between the last two, and every parameter the campaigns determine over time with its 95 % band.

Units on every axis: mm and degrees (each panel says which).
"""

from __future__ import annotations

import math

import numpy as np

from pmcal.history import Z95, Change, Record, determined, estimates, history_table, unit_of
from pmcal.reports.html import Report, matplotlib_agg

BLUE, RED, GREY = "#2b6cb0", "#c53030", "#718096"
COLUMNS = 4


def p_text(p: float) -> str:
    """A p-value for people: ``p = 0.012``, or ``p < 1e-12``."""
    return "p < 1e-12" if p < 1e-12 else f"p = {p:.2g}"


def plotted(records: list[Record], changes: list[Change] | None) -> list[str]:
    """Flagged parameters first, then those the last campaign determines (in the record's order)."""
    last = records[-1]
    flagged = [c.name for c in changes or [] if c.flagged]
    return flagged + [n for n in last.names if n not in flagged and determined(last, n)]


def history_report(records: list[Record], changes: list[Change] | None, folder: str, alpha: float) -> Report:
    """The report (write it with ``.write(path)``)."""
    matplotlib_agg()
    import matplotlib.pyplot as plt

    last = records[-1]
    rep = Report(f"Calibration history: {last.machine}",
                 f"{len(records)} calibrations in {folder}, {records[0].date:%Y-%m-%d %H:%M} to "
                 f"{last.date:%Y-%m-%d %H:%M} UTC; model {last.model}")
    flagged = [c for c in changes or [] if c.flagged]
    if changes is None:
        rep.card("One calibration: nothing to compare yet", ["File the next one with 'pmcal identify ... --history "
                                                             f"{folder}'."])
    elif flagged:
        rep.card(f"{len(flagged)} parameter(s) moved since the previous calibration", [
            f"{c.name}: {c.estimate:+.4g} {unit_of(c.name, records[-1])} (+- {Z95 * c.estimate_std:.2g} at 95 %), "
            f"{p_text(c.p_value)} (family-wise, alpha {alpha:g})"
            + (f"; it estimates {estimates(last, c.name)}" if estimates(last, c.name) else "") for c in flagged],
            css="bad")
    else:
        rep.card("Nothing moved since the previous calibration", [
            f"No parameter changed beyond the noise of the two calibrations (family-wise false-flag rate {alpha:g})."],
            css="ok")
    rep.paragraph("Test: the change of the parameter vector between the last two calibrations, with the "
                  "covariance of both, is explained by as few single-parameter changes as possible (forward "
                  "selection under the full covariance, Bonferroni over the parameters still in play). Marginal "
                  "intervals of correlated parameters are wide, so a change column can look small next to its "
                  "+-95% and still be flagged: the flag uses what the data say about that parameter alone.",
                  css="note")
    names = plotted(records, changes)
    if names:
        rep.heading("Parameters over time")
        rows = math.ceil(len(names) / COLUMNS)
        fig, axes = plt.subplots(rows, COLUMNS, figsize=(3.2 * COLUMNS, 2.3 * rows), squeeze=False)
        x = np.arange(len(records))
        labels = [f"{r.date:%Y-%m-%d}\n{r.date:%H:%M}" for r in records]
        moved = {c.name for c in flagged}
        by_name = {c.name: c for c in changes or []}
        for ax, n in zip(axes.flat, names):
            have = [i for i, r in enumerate(records) if n in r.names]
            v = np.array([records[i].value[records[i].names.index(n)] for i in have])
            s = np.array([records[i].std[records[i].names.index(n)] for i in have])
            color = RED if n in moved else BLUE
            xi = x[have]
            ax.fill_between(xi, v - Z95 * s, v + Z95 * s, color=color, alpha=0.18, lw=0)
            ax.errorbar(xi, v, yerr=Z95 * s, fmt="o-", color=color, ms=4, lw=1.2, capsize=3)
            c = by_name.get(n)
            if c is not None and c.flagged and len(have) >= 2 and have[-1] == len(records) - 1:
                # the change the test attributes to this parameter alone, from the previous value
                ax.errorbar([xi[-1] + 0.12], [c.previous + c.estimate], yerr=[Z95 * c.estimate_std], fmt="D",
                            color="#1a202c", ms=5, capsize=3, label="previous + attributed change")
                ax.legend(fontsize=6, loc="best")
            ax.set_title(f"{n} ({unit_of(n, records[-1])})" + ("  moved" if n in moved else ""), fontsize=9,
                         color=color, fontweight="bold" if n in moved else "normal")
            ax.set_xticks(x)
            ax.set_xticklabels(labels if len(records) <= 6 else [lb if i in (0, len(x) - 1) else "" for i, lb in
                                                                   enumerate(labels)], fontsize=7)
            ax.tick_params(axis="y", labelsize=7)
            ax.grid(alpha=0.3)
            ax.set_xlim(-0.4, len(records) - 0.4)
        for ax in list(axes.flat)[len(names):]:
            ax.axis("off")
        fig.tight_layout()
        hidden = len(last.names) - len(names)
        rep.figure(fig, "Each parameter at every calibration with its 95 % interval (band); red: moved between the "
                        "last two, with the change the test attributes to it alone (black diamond: previous value + "
                        "that change, its 95 % interval; the marginal estimate shares a change with correlated "
                        "parameters). " + (f"{hidden} parameters the campaigns do not determine (held near the design "
                                        "value by their tolerance prior) are in the table only." if hidden else ""))
    rep.heading("Last calibration and change since the previous one")
    header, rows = history_table(records, changes)
    rep.table(header, rows, left_cols=2)
    rep.heading("Calibrations")
    rep.table(["date (UTC)", "record", "campaign file", "SHA-256", "poses", "residual RMS mm", "tracker noise mm"],
              [[f"{r.date:%Y-%m-%d %H:%M:%S}", r.path.rsplit("/", 1)[-1], str(r.campaign.get("file", "")),
                str(r.campaign.get("sha256", ""))[:16],
                r.campaign.get("n_poses") if r.campaign.get("n_poses") is not None else "–",
                float(r.fit.get("residual_rms_mm", math.nan)),
                float(r.noise_mm) if r.noise_mm is not None else math.nan]
               for r in records], left_cols=4)
    return rep
