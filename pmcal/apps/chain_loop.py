"""Twin in the loop for a machine folder (``pmcal --machine DIR loop``): the task site's error (position
in mm, orientation in deg, both for a mixed task) before and after a compensation table is pushed to a mock PLC, as :mod:`pmcal.apps.ocpm.plc_loop` does for
ocpm_2dof's pointing error.

1. The folder's twin with geometric errors plays the real machine: each error drawn normal with the size
   machine.toml ``[errors]`` gives it, from ``--seed`` (the errors ``pmcal --machine DIR demo --seed`` draws),
   none, or a parameters file.
2. The demo's calibration on it (:mod:`pmcal.chain`): a D-optimal campaign of :data:`CAMPAIGN_POSES` poses
   measured with the tracker noise of machine.toml, identification of the base set, and the compensation
   table (format 4) over the ``[table]`` axes, version 2: by default corrections added to the controller's
   own nominal inverse kinematics (``[table] reference = "controller"``, nReference 2).
3. A strict mock PLC on 127.0.0.1 (ADS or Modbus TCP) starts with the nominal table, version 1: every
   correction 0 (an absolute table: the nominal IK's commands), the controller as commissioned.
4. Held-out targets drawn uniformly inside the table's grid. For each, the PLC's FB_CompTableLookup result is
   read back over the transport; the command is the controller's nominal IK (the nominal twin's) plus that
   correction, driven on the true twin; the virtual tracker measures the nests and the task site follows
   from their rigid fit (:meth:`pmcal.twin.closed_chain.ClosedChainTwin.task_from_reading`).
5. The identified table is pushed through the bridge (:func:`pmcal.bridge.transfer.push`), the same targets
   measured again; and the identified machine's own inverse kinematics (no table) for comparison.

Units: mm and degrees; errors are, per family of the task's coordinates, the distance of the task site from its
target over the position coordinates (mm) and the norm of its angle differences (deg).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field

import numpy as np

from pmcal import progress
from pmcal.apps.twin_loop import NOMINAL_VERSION, default_links, error_summary, plc_lookup
from pmcal.bridge.comptable import CompTable
from pmcal.bridge.errors import BridgeError
from pmcal.bridge.plc_types import LOOKUP_WRITES
from pmcal.bridge.transfer import PushReport, push
from pmcal.chain import campaign, compensate, compensation_table, identify, plan, random_errors, table_refusal
from pmcal.errors import InputError, RunError
from pmcal.mechanism.task_space import error_families, task_difference
from pmcal.studies.chain_demo import CAMPAIGN_POSES

#: version of the identified table pushed over the nominal one
PUSHED_VERSION = NOMINAL_VERSION + 1
#: held-out targets of the loop (as the seeded loop's test orientations)
DEFAULT_TARGETS = 24
#: the held-out targets' random stream: ``seed + TARGET_SEED`` (the demo's held-out offset)
TARGET_SEED = 1000


@dataclass
class LoopCalibration:
    """What the loop pushes and what it is judged against. truth : the twin's geometric errors (mm / deg).
    result : the identification (:class:`pmcal.calib.closed_chain.ChainIdentResult`). table : the
    compensation table (version :data:`PUSHED_VERSION`). poses : campaign poses. timings : s per step."""

    truth: dict
    result: object
    table: CompTable
    poses: int
    timings: dict = field(default_factory=dict)


def calibrate(machine, errors: str | dict = "random", seed: int = 1, nodes=None,
              poses: int = CAMPAIGN_POSES) -> LoopCalibration:
    """The demo's calibration (:func:`pmcal.studies.chain_demo.chain_demo`) of ``machine``'s twin with
    ``errors`` (``"random"``: drawn from ``seed`` as the demo draws them; ``"none"``; or ``{key: value}``):
    planned campaign, identification, and the compensation table over ``nodes`` per [table] axis (default
    machine.toml's). An :class:`pmcal.errors.InputError` if the machine gets no table."""
    check_table(machine)
    timings = {}
    t0 = time.perf_counter()
    if errors == "random":
        truth = random_errors(machine, np.random.default_rng(seed))
    else:
        truth = {} if errors == "none" else dict(errors)
    progress.status(f"planning and measuring {poses} poses on the twin of {machine.name}")
    design = plan(machine, poses, seed=seed)
    meas, _ = campaign(machine, poses, seed=seed, errors=truth, commands=design.commands)
    timings["campaign"] = time.perf_counter() - t0
    progress.status(f"identifying {len(machine.twin.error_keys)} errors from {len(meas)} poses")
    res = identify(machine, meas)
    timings["identify"] = time.perf_counter() - t0 - timings["campaign"]
    table = compensation_table(machine, res.params, PUSHED_VERSION, nodes)
    timings["table"] = time.perf_counter() - t0 - timings["campaign"] - timings["identify"]
    return LoopCalibration(truth, res, table, len(meas), timings)


def check_table(machine) -> None:
    """An :class:`pmcal.errors.InputError` (one line, what the machine gets instead) if ``machine`` gets no
    compensation table (:func:`pmcal.chain.table_refusal`): no loop without one."""
    why = table_refusal(machine)
    if why:
        raise InputError(why, field="--machine")


def nominal_table(machine, table: CompTable) -> CompTable:
    """The controller as commissioned, on ``table``'s grid, version :data:`NOMINAL_VERSION`: every correction
    0 (a table of corrections to the controller's IK), or the nominal twin's inverse kinematics at the nodes
    (a table of absolute commands). Validated."""
    values = np.zeros_like(table.values)
    if not table.controller_reference:
        spec = machine.spec
        order = [spec.table_axes.index(c) for c in spec.task.coordinates]
        nodes = table.nodes().reshape(-1, table.n_axes)[:, order]
        values = machine.twin.inverse(nodes, None).reshape(table.values.shape)
    return CompTable(machine=table.machine, version=NOMINAL_VERSION, axes=table.axes, motors=table.motors,
                     values=values, reference=table.reference).validate()


def grid_targets(machine, table: CompTable, count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` targets (count, C) in the machine's task coordinates, uniform inside the table's grid box."""
    coords = machine.spec.task.coordinates
    lo = np.array([a.min for a in table.axes])
    hi = np.array([a.max for a in table.axes])
    points = rng.uniform(lo, hi, (count, table.n_axes))
    return points[:, [[a.column for a in table.axes].index(c) for c in coords]]


@dataclass
class TaskError:
    """Sizes (n,) of the task site's errors from its targets, per error family of the task (unit -> array:
    ``"mm"`` position, ``"deg"`` orientation, :func:`pmcal.mechanism.task_space.error_families`): as the
    tracker measures them (the twin's true ones for a machine whose tracker reading does not fix the task
    site), and true; the commands driven."""

    measured: dict
    true: dict
    commands: np.ndarray

    @property
    def measured_mm(self) -> np.ndarray:
        return self.measured["mm"]

    @property
    def true_mm(self) -> np.ndarray:
        return self.true["mm"]

    def summary(self) -> dict:
        out = {}
        for unit in self.measured:
            out.update(error_summary(self.measured[unit], self.true[unit], unit))
        return out


def measure_task(machine, truth: dict, commands: np.ndarray, task: np.ndarray,
                 rng: np.random.Generator) -> TaskError:
    """Drive the true twin (errors ``truth``) to ``commands`` (n, M), read the nests with the tracker
    (noise of machine.toml, from ``rng``) and take the task site from them: its error from ``task`` in each
    of the task's error families (mm, deg)."""
    twin, coords = machine.twin, machine.spec.task.coordinates
    reached = twin.forward(commands, truth)
    if not np.isfinite(reached).all():
        raise RunError(f"the twin of {machine.name} did not assemble at every commanded pose")

    def sizes(where: np.ndarray) -> dict:
        d = task_difference(where, task, coords)
        return {unit: size(d, coords) for _, unit, _, size in error_families(coords)}

    true = sizes(reached)
    if not twin.reading_fixes_task:
        return TaskError(true, true, commands)
    return TaskError(sizes(twin.task_from_reading(twin.measure(commands, truth, rng))), true, commands)


@dataclass
class ChainLoopResult:
    """Before/after the push, and the identified IK without a table, at the held-out ``task`` targets."""

    machine: str
    transport: str
    task: np.ndarray
    before: TaskError
    after: TaskError
    direct: TaskError
    push: PushReport
    table: CompTable
    table_version: int
    calibration: LoopCalibration
    by_tracker: bool
    extra: dict = field(default_factory=dict)

    def summary(self) -> dict:
        t, res = self.table, self.calibration.result
        return {"machine": self.machine, "transport": self.transport, "targets": int(len(self.task)),
                "grid": list(t.shape), "axes": [f"{a.column} {a.min:g}..{a.max:g}" for a in t.axes],
                "reference": "controller" if t.controller_reference else "none",
                "table_version": self.table_version, "measured_by": "tracker" if self.by_tracker else "twin",
                "before": self.before.summary(), "after": self.after.summary(),
                "direct_no_table": self.direct.summary(),
                "push": {k: v for k, v in asdict(self.push).items() if k in ("result", "message", "timings_s")},
                "identification": {"campaign_poses": self.calibration.poses, "errors": len(res.params),
                                   "base_errors": len(res.base), "residual_rms_mm": float(res.residual_rms_mm),
                                   "chi2_per_dof": float(res.chi2_per_dof)},
                **self.extra}


def run_chain_loop(mock, machine, cal: LoopCalibration, *, n_targets: int = DEFAULT_TARGETS, seed: int = 1,
                   link_factory=None) -> ChainLoopResult:
    """Run the loop against a started mock PLC (:class:`pmcal.bridge.simulator.ads_mock.AdsMockPlc` or Modbus):
    seed it with :func:`nominal_table`, measure ``n_targets`` held-out targets (:func:`grid_targets`, from
    ``seed + TARGET_SEED``) driven by the PLC's lookups, push ``cal.table``, measure them again, and once
    more driven by the identified machine's inverse kinematics. ``link_factory(mock, writes)`` makes the
    client links (default: the mock's own transport)."""
    twin, coords = machine.twin, machine.spec.task.coordinates
    table = cal.table
    rng = np.random.default_rng(seed + TARGET_SEED)
    task = grid_targets(machine, table, n_targets, rng)
    points = task[:, [coords.index(a.column) for a in table.axes]]
    controller = twin.inverse(task, None)                   # the controller's own nominal IK
    link_factory = link_factory or default_links
    mock.twin.configure_for(table)                          # the PLC's MACHINE, NMOTORS, CORRECTIONS
    mock.twin.seed(nominal_table(machine, table))

    def lookups() -> tuple[np.ndarray, np.ndarray, int]:
        with link_factory(mock, LOOKUP_WRITES) as link:
            values, version, correction = plc_lookup(link, points, tuple(a.column for a in table.axes))
        return values, controller + values if correction else values, version

    t0 = time.perf_counter()
    _, cmd, version = lookups()
    if version != NOMINAL_VERSION:
        raise BridgeError(f"the PLC answered from table version {version}, not the nominal {NOMINAL_VERSION}")
    before = measure_task(machine, cal.truth, cmd, task, rng)
    t1 = time.perf_counter()
    report = push(link_factory(mock, None), table)
    values, cmd, version = lookups()
    after = measure_task(machine, cal.truth, cmd, task, rng)
    t2 = time.perf_counter()
    direct = measure_task(machine, cal.truth, compensate(machine, cal.result.params, task), task, rng)
    timings = {**cal.timings, "before": t1 - t0, "push_and_after": t2 - t1,
               "direct": time.perf_counter() - t2}
    return ChainLoopResult(machine.name, mock.transport, task, before, after, direct, report, table, version, cal,
                           twin.reading_fixes_task, extra={"plc_equals_table_lookup": bool(np.array_equal(values,
                                                                                             table.lookup(points))),
                                              "timings_s": timings})


def loop(args) -> int:
    """``pmcal --machine DIR loop [--transport ads|modbus] [--errors random|none|PARAMS.json] [--seed S]
    [--targets N] [--grid N1,N2,..] [--json OUT.json]``: calibrate the folder's twin, run the loop on a mock
    PLC started here, print the table of errors (and write the summary)."""
    from pmcal.apps.chain_commands import error_set, parse_nodes
    from pmcal.apps.twin_loop import check_target_count, loopback_mock, state_lines
    from pmcal.fileio import write_json

    machine = args.selected_machine
    check_table(machine)
    check_target_count(args.targets)
    t0 = time.perf_counter()
    cal = calibrate(machine, error_set(machine, args.errors), args.seed, parse_nodes(args.grid))
    with loopback_mock(args.transport) as mock:
        try:
            res = run_chain_loop(mock, machine, cal, n_targets=args.targets, seed=args.seed)
        except BridgeError as exc:
            print(f"pmcal: failed: twin loop over {args.transport}: {exc}")
            return exc.exit_status
    res.extra["timings_s"]["total"] = time.perf_counter() - t0
    s = res.summary()
    kind = "corrections to the controller's nominal IK" if s["reference"] == "controller" else "absolute commands"
    ident = s["identification"]
    print(f"twin in the loop over {res.transport} (mock PLC at {mock.target}), machine {machine.name}, "
          f"{s['targets']} targets inside the table {'x'.join(map(str, s['grid']))} v{res.table_version} "
          f"({kind}); errors identified from {ident['campaign_poses']} planned poses ({ident['base_errors']} of "
          f"{ident['errors']} in the base set, residual {ident['residual_rms_mm']:.4f} mm rms):")
    for name, unit, _, _ in error_families(machine.spec.task.coordinates):
        print("\n".join(state_lines(s, f"{name} error" if res.by_tracker else f"true {name} error", unit)))
    print(f"  push: {s['push']['message']}; PLC values equal the table's lookup: "
          f"{s['plc_equals_table_lookup']}; {s['timings_s']['total']:.1f} s")
    if args.json:
        write_json(args.json, s, indent=1)
    return 0
