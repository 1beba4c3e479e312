"""Twin in the loop: the digital twin plays the machine behind a mock PLC, before and after a push.

The mock PLC starts with the nominal table (version 1: the controller as commissioned, no
calibration). For each test orientation the twin asks the PLC for motor targets through
FB_CompTableLookup (over ADS or Modbus), drives to them, and the virtual laser tracker measures the
platform; the pointing error is the angle between the measured and the wanted platform normal. Then
the compensation table is pushed through the bridge and the same orientations are measured again.

Units: deg for orientations, commands and pointing errors; mm inside the tracker and the twin.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from pmcal.bridge.comptable import CompTable
from pmcal.mechanism.ocpm.config import Geometry, default_geometry
from pmcal.mechanism.ocpm.params import ErrorSet
from pmcal.bridge.errors import BridgeError
from pmcal.bridge.link import PlcLink
from pmcal.bridge.plc_types import LOOKUP_WRITES
from pmcal.bridge.transfer import PushReport, push
from pmcal.apps.twin_loop import (NOMINAL_VERSION, check_target_count, default_links, error_summary,  # noqa: F401
                                  loopback_mock, plc_lookup, state_lines)

#: 5 deg in phi, 2 deg in theta (as ``pmcal compensate --table``)
DEFAULT_GRID = (73, 31)


@dataclass
class Pointing:
    """Pointing errors (deg) at the test orientations: as the tracker measures them, and true."""

    measured_deg: np.ndarray
    true_deg: np.ndarray
    commands_deg: np.ndarray

    def summary(self) -> dict:
        return error_summary(self.measured_deg, self.true_deg, "deg")


@dataclass
class LoopResult:
    """Before/after the push, plus the compensation evaluated directly at the targets (no table)."""

    transport: str
    phi_deg: np.ndarray
    theta_deg: np.ndarray
    before: Pointing
    after: Pointing
    direct: Pointing
    push: PushReport
    table_version: int
    grid: tuple[int, int]
    extra: dict = field(default_factory=dict)

    def summary(self) -> dict:
        return {"transport": self.transport, "targets": int(len(self.phi_deg)), "grid": list(self.grid),
                "table_version": self.table_version, "before": self.before.summary(),
                "after": self.after.summary(), "direct_no_table": self.direct.summary(),
                "push": {k: v for k, v in asdict(self.push).items() if k in ("result", "message", "timings_s")},
                **self.extra}


def nominal_table(grid: tuple[int, int], geom: Geometry | None = None, version: int = NOMINAL_VERSION,
                  max_step_deg: float = 15.0) -> CompTable:
    """The uncalibrated controller as a table: nominal inverse kinematics on the grid (deg)."""
    from pmcal.mechanism.ocpm.kinematics import nominal_ik

    geom = geom or default_geometry()
    return _table(lambda p, t: np.rad2deg(nominal_ik(np.deg2rad(p), np.deg2rad(t), geom)), grid, geom,
                  version, max_step_deg)


def compensation_table(errors: ErrorSet, grid: tuple[int, int], version: int, geom: Geometry | None = None,
                       max_step_deg: float = 15.0) -> CompTable:
    """Whole-closed-chain compensation of the machine with ``errors`` on the grid (deg), validated."""
    from pmcal.calib.ocpm.fullchain import chain_commands_deg
    from pmcal.twin.ocpm.forward import FullChainModel

    geom = geom or default_geometry()
    model = FullChainModel(geom)
    return _table(lambda p, t: chain_commands_deg(model, errors, p, t), grid, geom, version, max_step_deg)


def _table(fill, grid, geom: Geometry, version: int, max_step_deg: float) -> CompTable:
    return CompTable.from_setpoints(fill, machine="ocpm_2dof", version=version, n_phi=grid[0], n_theta=grid[1],
                                    theta_range_deg=(0.0, float(np.rad2deg(geom.theta_max))),
                                    motor_limits_deg=(float(np.rad2deg(geom.motor_min)),
                                                      float(np.rad2deg(geom.motor_max))),
                                    max_step_deg=max_step_deg).validate()


def plc_commands(link: PlcLink, phi_deg: np.ndarray, theta_deg: np.ndarray) -> tuple[np.ndarray, int]:
    """Motor targets (N, 2) deg that FB_CompTableLookup gives for the orientations, and the table version."""
    out, version, _ = plc_lookup(link, np.stack([phi_deg, theta_deg], axis=-1), ("phi_deg", "theta_deg"))
    return out[:, :2], version


def measure(twin, tracker, commands_deg: np.ndarray, phi_deg: np.ndarray, theta_deg: np.ndarray) -> Pointing:
    """Drive the twin to the commands, measure with the tracker, pointing errors (deg) vs the targets."""
    from pmcal.mechanism.rigid import fit_pose
    from pmcal.mechanism.rotations import pointing_error, tilt_torsion

    state = twin.reach(commands_deg)
    if not np.all(state.converged):
        raise BridgeError("the twin did not assemble at every commanded pose")
    wanted = tilt_torsion(np.deg2rad(phi_deg), np.deg2rad(theta_deg))
    _, R_meas, _ = fit_pose(tracker.measure(state.targets), twin.geom.targets)
    return Pointing(np.rad2deg(pointing_error(R_meas, wanted)), np.rad2deg(pointing_error(state.R, wanted)),
                    np.asarray(commands_deg, float))


def run_loop(mock, errors: dict | ErrorSet, table: CompTable | None = None, *, n_targets: int = 24,
             grid: tuple[int, int] = DEFAULT_GRID, seed: int = 1, sigma_mm: float | None = None,
             link_factory=None) -> LoopResult:
    """Run the loop against a started mock PLC (:class:`pmcal.bridge.simulator.ads_mock.AdsMockPlc` or Modbus).

    ``errors``: the twin's real geometric errors (interface keys, mm and deg, or an ErrorSet);
    ``table``: what to push (default: the whole-chain compensation of ``errors`` on ``grid``).
    ``link_factory(mock, writes)`` makes the client links (default: the mock's own transport).
    """
    from pmcal.calib.ocpm.fullchain import chain_commands_deg
    from pmcal.twin.ocpm.forward import FullChainModel
    from pmcal.twin.ocpm.campaign import plan_orientations
    from pmcal.twin.ocpm.machine import Twin
    from pmcal.twin.tracker import LaserTracker

    geom = default_geometry()
    if not isinstance(errors, ErrorSet):
        errors = ErrorSet.from_dict(errors, geom.n_limbs, geom.actuated)
    rng = np.random.default_rng(seed)
    phi, theta = plan_orientations(n_targets, float(np.rad2deg(geom.theta_max)), rng)
    twin = Twin(errors, geom)
    tracker = LaserTracker(geom.sigma_mm if sigma_mm is None else sigma_mm, rng)
    if table is None:
        table = compensation_table(errors, grid, NOMINAL_VERSION + 1, geom)
    link_factory = link_factory or default_links
    mock.twin.seed(nominal_table((table.n_phi, table.n_theta), geom))

    with link_factory(mock, LOOKUP_WRITES) as link:
        cmd, version = plc_commands(link, phi, theta)
    assert version == NOMINAL_VERSION
    before = measure(twin, tracker, cmd, phi, theta)
    report = push(link_factory(mock, None), table)
    with link_factory(mock, LOOKUP_WRITES) as link:
        cmd, version = plc_commands(link, phi, theta)
    after = measure(twin, tracker, cmd, phi, theta)
    exact = table.interpolate(phi, theta)
    direct = measure(twin, tracker, chain_commands_deg(FullChainModel(geom), errors, phi, theta), phi, theta)
    return LoopResult(mock.transport, phi, theta, before, after, direct, report, version,
                      (table.n_phi, table.n_theta),
                      extra={"plc_equals_table_interpolation": bool(np.array_equal(cmd, exact))})


def loop(args) -> int:
    """``pmcal loop``: start a mock PLC, run the loop, print (and optionally write) the result."""
    from pmcal.apps.ocpm.twin import machine_errors
    from pmcal.apps.ocpm.calib import parse_grid
    from pmcal.fileio import write_json

    check_target_count(args.targets)
    errors = machine_errors(args)
    grid = parse_grid(args.grid)
    table = None
    if args.table:
        table = CompTable.load(args.table).validate(active_version=NOMINAL_VERSION)
        grid = (table.n_phi, table.n_theta)
    with loopback_mock(args.transport) as mock:
        try:
            res = run_loop(mock, errors, table, n_targets=args.targets, grid=grid, seed=args.seed)
        except BridgeError as exc:
            print(f"pmcal: failed: twin loop over {args.transport}: {exc}")
            return exc.exit_status
    s = res.summary()
    print(f"twin in the loop over {res.transport} (mock PLC at {mock.target}), {s['targets']} orientations, "
          f"table {grid[0]}x{grid[1]} v{res.table_version}:")
    print("\n".join(state_lines(s, "pointing error", "deg")))
    print(f"  push: {s['push']['message']}; PLC targets equal the table's interpolation: "
          f"{s['plc_equals_table_interpolation']}")
    if args.json:
        write_json(args.json, s, indent=1)
    return 0
