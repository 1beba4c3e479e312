"""The whole job on a machine folder (``pmcal --machine DIR demo``): a planned campaign on its twin with
random geometric errors, identification, compensation of held-out targets, and what it gained, judged on
the twin's true machine. Units: mm and degrees.

:func:`chain_demo` computes a :class:`ChainDemo`; :mod:`pmcal.reports.chain_demo` turns it into the HTML
report; :func:`run_chain_demo` writes the folder (``report.html``, the files of every step, ``summary.json``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pmcal import progress
from pmcal.calib.closed_chain import compensate_targets, law_directions, rms_band
from pmcal.chain import (campaign, compensation_table, dominant_line, identify, params_document, plan, random_errors,
                         sample_targets, table_refusal)
from pmcal.errors import InputError
from pmcal.fileio import atomic_directory, write_json
from pmcal.io_chain import write_measurements, write_plan, write_setpoints, write_targets
from pmcal.mechanism.task_space import error_families, position_distance, rms, task_difference


def carrying(weights: np.ndarray, share: float = 0.999) -> int:
    """How many of the largest ``weights`` (sorted, largest first) carry ``share`` of their sum."""
    total = float(np.sum(weights))
    return int(np.searchsorted(np.cumsum(weights), share * total) + 1) if total > 0 else 0


#: poses of the demo's campaign, held-out targets of its evaluation
CAMPAIGN_POSES, HELD_OUT = 48, 60


@dataclass
class ChainDemo:
    """What the demo computed (mm and degrees; task errors per held-out target).

    truth : the twin's geometric errors. design : the planned campaign
    (:class:`pmcal.calib.chain_design.CampaignDesign`). meas : its measurements. result : the
    identification (:class:`pmcal.calib.closed_chain.ChainIdentResult`). task : (n, C) held-out targets.
    error_nominal, error_compensated : (n, C) task-coordinate errors of the true machine driven by the
    nominal inverse kinematics and by the compensated commands. predicted : (n, C) standard deviation of
    the compensated error the identification's covariance predicts. predicted_law : per error family
    (position, orientation) the weights of the law of the compensated mean square error over campaigns
    (:meth:`pmcal.calib.closed_chain.ChainIdentResult.predicted_task_law`). table : the compensation table for the
    PLC (:class:`pmcal.bridge.comptable.CompTable`; None when the machine gets none, ``table_note`` says
    why). inside : the held-out targets inside its grid. error_table : (inside, C) the true machine's error
    driven by the controller's nominal inverse kinematics plus the table's correction (the PLC's lookup).
    timings : s per step. unseen : errors that move the task point but no tracker reading
    (:func:`pmcal.chain.unseen_task_errors`). dominant : the barely seen combination of errors that carries
    the predicted task error, or None (:func:`pmcal.chain.dominant_task_uncertainty`).
    """

    machine: object
    seed: int
    truth: dict
    design: object
    meas: object
    result: object
    task: np.ndarray
    commands_nominal: np.ndarray
    commands_compensated: np.ndarray
    error_nominal: np.ndarray
    error_compensated: np.ndarray
    predicted: np.ndarray
    predicted_law: dict = field(default_factory=dict)
    table: object = None
    table_note: str = ""
    inside: np.ndarray | None = None
    error_table: np.ndarray | None = None
    timings: dict = field(default_factory=dict)
    unseen: list = field(default_factory=list)
    dominant: dict | None = None

    @property
    def coordinates(self) -> tuple[str, ...]:
        return self.machine.spec.task.coordinates

    def position_error(self, err: np.ndarray) -> np.ndarray:
        """Distance (n,) mm of the task site from its target, over the position coordinates."""
        return position_distance(err, self.coordinates)

    def summary(self) -> dict:
        """The figures of the report's first card (JSON-ready), in the task's own units: for each error family
        the task holds (:func:`pmcal.mechanism.task_space.error_families`) ``<family>_rms_before_<unit>``,
        ``_max_before_``, ``_rms_after_``, ``_max_after_``, ``_rms_predicted_`` (position in mm, orientation
        in deg; a mixed task has both), ``<family>_predicted_band_<unit>`` (the band [low, high] that 90 % of
        campaigns like this one end in, :func:`pmcal.calib.closed_chain.rms_band`) and
        ``<family>_predicted_directions`` (how many independent error directions carry the prediction: near 1,
        one campaign may well end at 2x the predicted RMS or at a tenth of it), ``<family>_predicted_law_<unit>2``
        (the law's largest weights, those that carry 99.9 % of it, unit^2: the mean square error over campaigns
        is ``sum w_i z_i^2``), and the same through the table (``<family>_rms_<unit>``)."""
        r, coords = self.result, self.coordinates
        out = {"machine": self.machine.name, "seed": self.seed, "campaign_poses": len(self.meas),
               "held_out_targets": len(self.task), "errors": len(r.params), "base_errors": len(r.base),
               "plan_gain": self.design.gain, "chi2_per_dof": r.chi2_per_dof, "residual_rms_mm": r.residual_rms_mm}
        table = None if self.table is None else {
            "axes": [f"{a.column} {a.min:g}..{a.max:g} ({a.n} nodes)" for a in self.table.axes],
            "reference": "controller" if self.table.reference is not None else "none",
            "targets_inside": int(self.inside.sum())}
        for name, unit, members, size in error_families(coords):
            before, after = size(self.error_nominal, coords), size(self.error_compensated, coords)
            idx = [i for i, c in enumerate(coords) if c in members]
            out.update({f"{name}_rms_before_{unit}": rms(before), f"{name}_max_before_{unit}": float(before.max()),
                        f"{name}_rms_after_{unit}": rms(after), f"{name}_max_after_{unit}": float(after.max()),
                        f"{name}_rms_predicted_{unit}": rms(np.sqrt(np.sum(self.predicted[:, idx] ** 2, axis=1)))})
            if name in self.predicted_law:
                weights = self.predicted_law[name]
                out.update({f"{name}_predicted_band_{unit}": list(rms_band(weights)),
                            f"{name}_predicted_directions": law_directions(weights),
                            f"{name}_predicted_law_{unit}2": [float(w) for w in weights[:carrying(weights)]]})
            if table is not None:
                through = size(self.error_table, coords)
                table.update({f"{name}_rms_{unit}": rms(through), f"{name}_max_{unit}": float(through.max())})
        out.update({"per_coordinate_rms_after": {c: rms(self.error_compensated[:, i]) for i, c in enumerate(coords)},
                    "table": table, "table_note": self.table_note, "timings_s": self.timings})
        return out

    #: compensated error above this multiple of the identification's prediction is warned about
    WORSE_THAN_PREDICTED = 3.0

    def warnings(self, summary: dict | None = None) -> list[str]:
        """What the demo must say besides its figures: an error family compensated to more than
        :data:`WORSE_THAN_PREDICTED` times what the identification predicted (the model misses something
        the twin has: the calibration would not hold on the machine either), errors the tracker cannot see
        that move the task point (:func:`pmcal.chain.unseen_task_errors`), a barely seen combination of errors
        that carries the predicted task error (:func:`pmcal.chain.dominant_task_uncertainty`), a failed held-out
        check."""
        s = summary or self.summary()
        out = []
        for name, u, _, _ in error_families(self.coordinates):
            after, predicted = s[f"{name}_rms_after_{u}"], s[f"{name}_rms_predicted_{u}"]
            if np.isfinite(predicted) and after > self.WORSE_THAN_PREDICTED * predicted:
                out.append(f"the compensated {name} error, {after:.4f} {u} RMS, is {after / predicted:.1f} times "
                           f"what the identification predicts ({predicted:.4f} {u}): the model misses something "
                           "the machine has (see the report's residuals)")
        unseen = self.unseen
        if unseen:
            out.append(f"{len(unseen)} error(s) move the task point but no tracker reading ({', '.join(unseen[:4])}"
                       f"{', ...' if len(unseen) > 4 else ''}): no compensation corrects them; the prediction counts "
                       "them at their [errors] size (put a nest on that part, or [errors] exclude it)")
        dominant = dominant_line(self.dominant, unseen)
        if dominant:
            out.append(dominant)
        held = self.result.info.get("held_out") or {}
        if held.get("passed") is False:
            out.append(f"the identification does not predict poses it did not fit: {held['rms_mm']:.4f} mm RMS "
                       f"where {held['predicted_rms_mm']:.4f} mm is predicted")
        return out

    def headline(self, summary: dict | None = None) -> str:
        """The demo's figures in one line, in the task's units: ``position error ... mm RMS (predicted ...)``
        and/or ``orientation error ... deg RMS (predicted ...)``, and through the PLC table."""
        s = summary or self.summary()
        fam = error_families(self.coordinates)
        parts = [f"{name} error on {s['held_out_targets']} held-out targets {s[f'{name}_rms_before_{u}']:.4f} -> "
                 f"{s[f'{name}_rms_after_{u}']:.4f} {u} RMS (predicted {s[f'{name}_rms_predicted_{u}']:.4f})"
                 for name, u, _, _ in fam]
        if s["table"]:
            parts.append("through the PLC table " + ", ".join(f"{s['table'][f'{name}_rms_{u}']:.4f} {u}"
                                                              for name, u, _, _ in fam)
                         + f" RMS on the {s['table']['targets_inside']} inside its grid")
        return "; ".join(parts)


def chain_demo(machine, seed: int = 1, out: Path | None = None) -> ChainDemo:
    """Run the demo's steps on ``machine`` (a :class:`pmcal.machines.Machine` folder), writing each step's
    file into ``out`` when given; progress on stderr."""
    twin = machine.twin
    rng = np.random.default_rng(seed)
    timings: dict[str, float] = {}
    steps = ("plan", "measure", "identify", "compensate", "table", "evaluate")
    with progress.progress(total=len(steps), desc="pmcal demo", unit="step") as bar:
        def step(name):
            bar.set_description(f"pmcal demo: {name}")
            timings[name] = time.perf_counter()

        def done(name):
            timings[name] = time.perf_counter() - timings[name]
            bar.update(1)

        step("plan")
        truth = random_errors(machine, rng)
        design = plan(machine, CAMPAIGN_POSES, seed=seed)
        done("plan")
        step("measure")
        meas, _ = campaign(machine, CAMPAIGN_POSES, seed=seed, errors=truth, commands=design.commands)
        done("measure")
        step("identify")
        res = identify(machine, meas)
        done("identify")
        step("compensate")
        task = sample_targets(machine, HELD_OUT, seed=seed + 1000)
        task, compensated = reachable_targets(machine, res.params, task)
        if not len(task):
            raise InputError(f"the identified machine reaches none of the {HELD_OUT} held-out targets the nominal "
                             f"one reaches (each named above): nothing to compensate; check that the motor ranges "
                             f"reach the workspace box with a margin", file=str(machine.spec.folder / "machine.toml"),
                             field="workspace")
        nominal = twin.inverse(task, None)
        done("compensate")
        step("table")
        coords = machine.spec.task.coordinates
        table, inside, err_table = None, None, None
        note = table_refusal(machine) or ""
        if not note:
            table = compensation_table(machine, res.params, version=1)
            order = [coords.index(a.column) for a in table.axes]
            lo, hi = np.array([a.min for a in table.axes]), np.array([a.max for a in table.axes])
            inside = np.all((task[:, order] >= lo) & (task[:, order] <= hi), axis=1)
            table_cmd = table.lookup(task[inside][:, order])
            if table.reference is not None:           # corrections to the controller's nominal IK
                table_cmd = nominal[inside] + table_cmd
            err_table = task_difference(twin.forward(table_cmd, truth), task[inside], coords)
        done("table")
        step("evaluate")
        err_nominal = task_difference(twin.forward(nominal, truth), task, coords)
        err_comp = task_difference(twin.forward(compensated, truth), task, coords)
        J = twin.task_jacobian(compensated, res.params, list(res.params))
        predicted = res.predicted_task_std(J)
        law = {name: res.predicted_task_law(J, [i for i, c in enumerate(coords) if c in members])
               for name, _, members, _ in error_families(coords)}
        done("evaluate")
    doc = params_document(machine, res, "measurements.csv")       # what the demo says of the result, as identify
    demo = ChainDemo(machine=machine, seed=seed, truth=truth, design=design, meas=meas, result=res, task=task,
                     commands_nominal=nominal, commands_compensated=compensated, error_nominal=err_nominal,
                     error_compensated=err_comp, predicted=predicted, predicted_law=law, table=table, table_note=note,
                     inside=inside, error_table=err_table, timings=timings, unseen=doc["unseen_by_tracker"],
                     dominant=doc["dominant_task_uncertainty"])
    if out is not None:
        spec = machine.spec
        write_plan(out / "plan.csv", spec, design.commands, [f"pmcal demo: D-optimal plan, seed {seed}"])
        write_measurements(out / "measurements.csv", spec, meas, [
            f"pmcal demo: machine {machine.name}, random errors of machine.toml's sizes, seed {seed}",
            "true errors (mm, deg): " + ", ".join(f"{k}={v:.6g}" for k, v in truth.items())])
        write_json(out / "params.json", doc)
        write_targets(out / "targets.csv", spec, task, [f"pmcal demo: held-out targets, seed {seed + 1000}"])
        write_setpoints(out / "setpoints.csv", spec, task, compensated,
                        ["pmcal demo: compensated commands (identified model's inverse kinematics)"])
        if table is not None:
            table.save(out / "table.json")
    return demo


def reachable_targets(machine, params, task: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The held-out targets (n, C) the machine with the identified errors ``params`` reaches, and its commands
    there (n, M); each one it does not reach (near the reach boundary, where the nominal machine still
    does) is left out with a warning line naming it and why."""
    commands = compensate_targets(machine.twin, dict(params), task)
    bad = np.flatnonzero(~np.isfinite(commands).all(axis=1))
    coords = machine.spec.task.coordinates
    for i in bad:
        _, why = machine.twin.inverse_report(task[i:i + 1], dict(params))
        where = ", ".join(f"{c}={v:.6g}" for c, v in zip(coords, task[i]))
        progress.warning(f"held-out target {i + 1} ({where}) left out: not reachable by the identified machine "
                         f"({why[0]})")
    keep = np.isfinite(commands).all(axis=1)
    return task[keep], commands[keep]


def run_chain_demo(machine, out: Path, seed: int) -> int:
    """``pmcal --machine DIR demo``: :func:`chain_demo` into the folder ``out`` (replaced as a whole), with
    the HTML report and ``summary.json``; one line of figures on stdout."""
    from pmcal.reports.chain_demo import chain_demo_report

    t0 = time.perf_counter()
    with atomic_directory(out) as tmp:
        demo = chain_demo(machine, seed, tmp)
        demo.timings["total"] = time.perf_counter() - t0
        summary = demo.summary()
        chain_demo_report(demo).write(tmp / "report.html")
        write_json(tmp / "summary.json", summary)
    print(f"pmcal demo: {out}/report.html in {time.perf_counter() - t0:.0f} s; {machine.name}: "
          f"{demo.headline(summary)}", flush=True)
    for line in demo.warnings(summary):
        progress.warning(line)
    return 0
