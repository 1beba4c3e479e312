"""A machine as data: ``machine.toml`` beside an MJCF model, read and validated at the edge.

A closed-chain machine is a folder (Menagerie layout): ``<name>.xml`` (the MJCF: kinematic tree, loops
closed by ``connect``/``weld`` equality constraints, a ``home`` keyframe), ``scene.xml`` and
``machine.toml`` holding only what the MJCF cannot say: which joints are motors (range, zero
convention), the tracker targets and what is measured of them, the task coordinates and the workspace to
sample, which geometric errors to identify, the tracker noise and the compensation-table axes. Every field
is documented in ``docs/machine_toml.md``.

:meth:`MachineSpec.load` reads the folder with ``tomllib`` and checks every name against the MJCF
(:mod:`pmcal.mechanism.mjcf_names`, no MuJoCo). Bad input raises :class:`pmcal.errors.InputError` naming
the file, the key and the fix. The seeded machines (``ocpm_2dof``, ``planar_2dof``) keep their own TOML
keys: a ``[machine] kind`` other than ``"chain"``, or a file without ``[[motors]]``, gives a spec with
``legacy=True`` (name, folder, model path and title only) that the application routes to their dedicated
code.

Units: motor commands in deg (revolute) or mm (prismatic); task coordinates in mm and deg as their column
names say; tracker noise in mm. Frames: task and target coordinates are in the model's world frame (the
machine's base frame, the tracker's frame after registration).

Example
-------
>>> from pmcal.mjcf import machine_dir
>>> spec = MachineSpec.load(machine_dir("delta_3dof"))
>>> [m.name for m in spec.motors], spec.targets, spec.task.coordinates      # doctest: +SKIP
(['m1', 'm2', 'm3'], ('nest1', 'nest2', 'nest3'), ('x_mm', 'y_mm', 'z_mm'))
"""

from __future__ import annotations

import math
import tomllib
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any, Mapping

from pmcal.errors import InputError
from pmcal.mechanism.mjcf_names import MjcfNames, read_names

#: Task coordinates a machine may use: position of the task site (mm) and orientation of its frame (deg),
#: ``R = Rz(rz) Ry(ry) Rx(rx)`` relative to the world frame; or the tilt-torsion pair (phi, theta) of the
#: site's z axis (:func:`pmcal.mechanism.rotations.tilt_torsion`).
TASK_COORDINATES = ("x_mm", "y_mm", "z_mm", "rx_deg", "ry_deg", "rz_deg", "phi_deg", "theta_deg")
#: The six components of a frame error: translation (mm) and rotation (deg) about the parent frame's axes.
ERROR_COMPONENTS = ("dx", "dy", "dz", "drx", "dry", "drz")
MOTOR_KINDS = {"revolute": ("hinge", "deg"), "prismatic": ("slide", "mm")}
MEASURES = ("position", "pose", "distance")
#: ``[tracker] reference`` of a ``"distance"`` measurement: what a reading is relative to
DISTANCE_REFERENCES = ("previous", "first")
#: ``[machine] kind`` values routed to the seeded machines' dedicated code.
LEGACY_KINDS = ("ocpm_2dof", "planar_2dof")

#: tracker or scale noise, mm (``[tracker] sigma_mm``, ``--noise``, ``--sigma``): above this a unit mix-up
#: (metres, micrometres) is likelier than the noise
NOISE_MAX_MM = 10.0
NOISE_MAX_WHY = "mm: a larger noise is likelier a unit mix-up, metres or micrometres"

#: the largest motion error (``[[motors]] sigma``, deg or mm) and why
MOTOR_SIGMA_MAX = (10.0, "deg or mm: a servo's repeatability; a larger one is a unit mix-up")
#: the largest prior size of an error (``[errors]``), by unit, and why
ERROR_SIZE_MAX = {"mm": (1000.0, "mm: a metre is no error of a drawing"), "deg": (180.0, "deg: half a turn")}

#: sections ``pmcal export-model`` writes into a calibrated machine's TOML: a record of the calibration
#: (source, date, identified values, named effects), not read by the machine's description
RECORD_SECTIONS = ("calibration", "effects")


@dataclass(frozen=True)
class MotorSpec:
    """One actuated joint.

    name : ``"m1"``, ``"m2"``, ... in the order of ``[[motors]]`` (CSV columns ``m1_cmd_deg`` / ``m1_cmd_mm``).
    joint : MJCF joint name (a hinge for ``revolute``, a slide for ``prismatic``).
    kind : ``"revolute"`` or ``"prismatic"``.
    unit : ``"deg"`` (revolute) or ``"mm"`` (prismatic): the unit of commands, ``range`` and ``zero``.
    range : (lo, hi) allowed commands, in ``unit``.
    zero : the command that puts the joint at qpos 0: joint position = command - zero (in ``unit``).
    sigma : the motor's motion error, 1 sigma in ``unit`` (the servo's positioning repeatability): the twin's
        campaigns hold each pose at the command plus such an error; 0: exact.
    """

    name: str
    joint: str
    kind: str
    unit: str
    range: tuple[float, float]
    zero: float = 0.0
    sigma: float = 0.0


@dataclass(frozen=True)
class TaskSpec:
    """Task coordinates: the pose of MJCF site ``site`` in the world frame (or in the frame of the site
    ``frame`` on the fixed base, the frame of the machine's drawing), as the columns ``coordinates`` (a
    subset of :data:`TASK_COORDINATES`, in the given order)."""

    site: str
    coordinates: tuple[str, ...]
    frame: str | None = None


@dataclass(frozen=True)
class ErrorSpec:
    """Which geometric errors to identify.

    frames : ``"all"`` (every body but the world, every site the chain or the tracker uses) or MJCF body /
        site names.
    exclude : names removed from ``frames``.
    components : which of :data:`ERROR_COMPONENTS` a body frame carries (a site carries the translations
        among them: a point has no orientation).
    motor_zero : identify one zero offset per motor (keys ``m1.dzero``, ...).
    position_mm, angle_deg, zero_deg, zero_mm : prior size (1 sigma) of each kind of error: the Tikhonov
        regularisation of identification and the size of random errors in studies.
    """

    frames: str | tuple[str, ...] = "all"
    exclude: tuple[str, ...] = ()
    components: tuple[str, ...] = ERROR_COMPONENTS
    motor_zero: bool = True
    position_mm: float = 1.0
    angle_deg: float = 0.3
    zero_deg: float = 1.0
    zero_mm: float = 1.0


@dataclass(frozen=True)
class ClosureSpec:
    """Compliance of the loop closures, for an over-constrained machine (optional ``[closures]``).

    With it, assembly minimises the elastic energy ``1/2 sum k_c |gap_c|^2 + 1/2 sum k_j (q_j - q0_j)^2``
    instead of solving the closures exactly: ``stiffness`` closure name -> N/mm (the others get
    ``default_n_per_mm``), and with ``joint_springs`` the passive joints that have an MJCF ``stiffness``
    (N/m or N m/rad, MuJoCo's units) act as springs about their ``springref``.
    """

    default_n_per_mm: float = 1.0
    stiffness: Mapping[str, float] = field(default_factory=lambda: MappingProxyType({}))
    joint_springs: bool = False


#: nodes per axis of a machine folder's compensation table, and the max step (deg or mm), unless [table] says
TABLE_NODES_DEFAULT = 9
TABLE_MAX_STEP_DEFAULT = 10.0
#: what a folder machine's table holds by default: corrections to the motion controller's own nominal IK
#: ("controller") or absolute commands ("none"); the largest correction and correction step (deg or mm)
TABLE_REFERENCES = ("controller", "none")
TABLE_MAX_CORRECTION_DEFAULT = 1.0
TABLE_MAX_CORRECTION_STEP_DEFAULT = 0.25


@dataclass(frozen=True)
class TableSpec:
    """``[table]`` grid of a compensation table: nodes per axis, the box it spans (per axis [lo, hi] in the
    axis' unit), the largest command change between neighbouring nodes allowed (deg or mm, every motor);
    what the table holds (``reference``: ``"controller"``, corrections to the motion controller's own
    nominal IK, or ``"none"``, absolute commands), and for corrections the largest correction and the
    largest change of a correction between neighbouring nodes (deg or mm, every motor)."""

    nodes: tuple[int, ...]
    box: Mapping[str, tuple[float, float]]
    max_step: float
    reference: str = "controller"
    max_correction: float = TABLE_MAX_CORRECTION_DEFAULT
    max_correction_step: float = TABLE_MAX_CORRECTION_STEP_DEFAULT
    #: the axes whose span machine.toml leaves to the default (the largest box inside the workspace the
    #: nominal machine reaches, ``pmcal.chain.table_box``), and whether ``max_correction`` is left to its
    #: default (from the error sizes and the machine's sensitivity, ``pmcal.chain.correction_bound``)
    box_default: tuple[str, ...] = ()
    max_correction_default: bool = False


@dataclass(frozen=True)
class MachineSpec:
    """A validated machine folder (see module docstring and ``docs/machine_toml.md``).

    name, title : short name (the folder's by default) and one-line description.
    folder, model_path : the folder and its MJCF file (absolute paths).
    motors : one :class:`MotorSpec` per actuated joint, M of them.
    targets : MJCF site names of the tracker nests, K of them (CSV columns ``t1_x`` ... ``tK_z``, mm).
    measure : ``"position"`` (each nest's position), ``"pose"`` (the platform pose from a rigid fit of
        the >= 3 nests) or ``"distance"`` (the distance between the two ``targets`` sites, read by a linear
        scale relative to a reference pose: ``reference``).
    reference : for ``measure = "distance"``: ``"previous"`` (each reading is the change of the distance
        since the previous pose of the campaign: a scale whose head is reset after each reading) or
        ``"first"`` (the change since the campaign's first pose: an incremental scale zeroed there).
    names : the machine's own names of errors (a paper's, an interface's) -> the frame-error keys each moves
        together with the same value (``[names]``; e.g. ``{"dtheta1": ("m1.dzero",)}``).
    task : :class:`TaskSpec`.
    workspace : task coordinate -> (lo, hi): the box campaigns and target lists sample (then filtered by
        reachability and motor ranges), in the coordinate's unit.
    errors : :class:`ErrorSpec`.
    sigma_mm : tracker noise, 1 sigma per coordinate, mm.
    table_axes : up to 3 task coordinates spanning a compensation table; empty: offline compensation of
        target lists only.
    home : name of the MJCF keyframe of an assembled configuration (the branch every solve stays on), or
        None: the model's default configuration (``qpos0``, assembled by the twin), when ``[machine] home``
        is not given and the model has no keyframe ``home``.
    closures : :class:`ClosureSpec` of an over-constrained machine, or None: closures solved exactly (a
        least-squares compromise with equal weights if they conflict).
    legacy : True for the seeded machines' TOML (only ``name``, ``folder``, ``model_path``, ``title``, ``kind``
        are set; the application routes them to their dedicated code).
    kind : ``"chain"`` or a legacy kind (``"ocpm_2dof"``, ``"planar_2dof"``).
    """

    name: str
    folder: Path
    model_path: Path
    title: str = ""
    motors: tuple[MotorSpec, ...] = ()
    targets: tuple[str, ...] = ()
    measure: str = "position"
    reference: str = "previous"
    names: Mapping[str, tuple[str, ...]] = field(default_factory=lambda: MappingProxyType({}))
    task: TaskSpec | None = None
    workspace: Mapping[str, tuple[float, float]] = field(default_factory=lambda: MappingProxyType({}))
    errors: ErrorSpec = field(default_factory=ErrorSpec)
    sigma_mm: float = 0.01
    table_axes: tuple[str, ...] = ()
    table: "TableSpec | None" = None
    home: str | None = "home"
    closures: ClosureSpec | None = None
    legacy: bool = False
    kind: str = "chain"

    @property
    def motor_columns(self) -> tuple[str, ...]:
        """CSV column names of the motor commands: ``m1_cmd_deg`` (revolute) / ``m1_cmd_mm`` (prismatic)."""
        return tuple(f"{m.name}_cmd_{m.unit}" for m in self.motors)

    @property
    def target_columns(self) -> tuple[str, ...]:
        """CSV column names of the tracker targets: ``t1_x, t1_y, t1_z, ..., tK_z`` (mm, world frame)."""
        return tuple(f"t{k + 1}_{c}" for k in range(len(self.targets)) for c in "xyz")

    @classmethod
    def load(cls, folder: str | Path) -> "MachineSpec":
        """Read and validate ``folder/machine.toml`` and its MJCF (see module docstring).

        Parameters
        ----------
        folder : a machine folder (or its ``machine.toml``).

        Raises
        ------
        pmcal.errors.InputError
            Missing folder or file, TOML syntax, a missing or wrong key: the message names the file, the key
            and what to write instead.
        """
        return _Loader(Path(folder)).spec()


def expand_names(names: Mapping[str, tuple[str, ...]], values: Mapping[str, float]) -> dict[str, float]:
    """Frame errors ``{frame key: value}`` of errors given by a machine's own names (``[names]``: name -> the
    frame-error keys it moves together by its value; keys moved by several names get the sum).

    >>> expand_names({"de1x": ("a.dx", "b.dx"), "dtheta1": ("m1.dzero",)}, {"de1x": 0.1})
    {'a.dx': 0.1, 'b.dx': 0.1, 'm1.dzero': 0.0}

    Raises KeyError for a name not in ``names``.
    """
    unknown = set(values) - set(names)
    if unknown:
        raise KeyError(f"unknown error name(s): {', '.join(sorted(unknown))} (known: {', '.join(names)})")
    out: dict[str, float] = {}
    for name, keys in names.items():
        for k in keys:
            out[k] = out.get(k, 0.0) + float(values.get(name, 0.0))
    return out


class _Loader:
    """Reads one machine.toml; every error names the file and the key."""

    def __init__(self, folder: Path):
        if folder.is_file() and folder.name == "machine.toml":
            folder = folder.parent
        self.folder = folder.resolve()
        self.path = self.folder / "machine.toml"
        self.file = str(self.path)
        if not folder.is_dir():
            raise InputError("machine folder not found (give a folder holding machine.toml and the MJCF)",
                             file=str(folder))
        try:
            self.doc = tomllib.loads(self.path.read_text(encoding="utf-8-sig"))     # a BOM (Windows editors) dropped
        except FileNotFoundError:
            raise InputError("file not found: a machine folder needs a machine.toml (docs/machine_toml.md)",
                             file=self.file) from None
        except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
            raise InputError(f"cannot read machine configuration ({exc})", file=self.file) from None
        except RecursionError:      # tomllib recurses per nesting level: [[[[... thousands deep
            raise InputError("cannot read machine configuration (arrays or tables nested too deep)",
                             file=self.file) from None
        self.names: MjcfNames | None = None

    # ------------------------------------------------------------------ helpers
    def err(self, key: str, message: str) -> InputError:
        return InputError(message, file=self.file, field=key)

    def table(self, key: str, required: bool = True) -> dict:
        v = self.doc.get(key)
        if v is None:
            if required:
                raise self.err(f"[{key}]", f"missing section [{key}] (docs/machine_toml.md)")
            return {}
        if not isinstance(v, dict):
            raise self.err(f"[{key}]", f"must be a table [{key}], got {type(v).__name__}")
        return v

    def known(self, tab: dict, where: str, keys: tuple[str, ...]) -> None:
        """Reject a key outside ``keys`` (a typo would otherwise be ignored silently)."""
        unknown = sorted(set(tab) - set(keys))
        if unknown:
            raise self.err(f"{where}.{unknown[0]}" if where else f"[{unknown[0]}]",
                           f"unknown key (known: {', '.join(keys)}; docs/machine_toml.md)")

    def text(self, tab: dict, key: str, where: str, default: Any = None, choices: tuple[str, ...] = ()) -> str:
        v = tab.get(key, default)
        if v is None:
            raise self.err(f"{where}.{key}", "missing key" + (f" (one of: {', '.join(choices)})" if choices else ""))
        if not isinstance(v, str) or not v:
            raise self.err(f"{where}.{key}", f"must be a non-empty string, got {v!r}")
        self.one_line(v, f"{where}.{key}")
        if choices and v not in choices:
            raise self.err(f"{where}.{key}", f"must be one of {', '.join(choices)}, got {v!r}")
        return v

    def one_line(self, v: str, key: str) -> None:
        """InputError unless ``v`` is one line without control characters: names and the title go into the
        comment lines of every file written (a newline there made the rest of the line a CSV row)."""
        if any(ord(c) < 32 or ord(c) == 127 for c in v):
            raise self.err(key, f"must be one line without control characters (it heads the files written), got {v!r}")

    def number(self, tab: dict, key: str, where: str, default: float | None = None,
               positive: bool = False, high: tuple[float, str] | None = None) -> float:
        """The number ``where.key``; ``high``: (largest value, why) it may take."""
        v = tab.get(key, default)
        if v is None:
            raise self.err(f"{where}.{key}", "missing key (a number)")
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise self.err(f"{where}.{key}", f"must be a finite number, got {v!r}")
        if positive and v <= 0:
            raise self.err(f"{where}.{key}", f"must be positive, got {v!r}")
        if high is not None and v > high[0]:
            raise self.err(f"{where}.{key}", f"must be at most {high[0]:g} ({high[1]}), got {v!r}")
        return float(v)

    def interval(self, v: Any, key: str) -> tuple[float, float]:
        if (not isinstance(v, list) or len(v) != 2 or any(isinstance(x, bool) or not isinstance(x, (int, float))
                                                         or not math.isfinite(x) for x in v)):
            raise self.err(key, f"must be [lo, hi] (two finite numbers), got {v!r}")
        if not v[0] < v[1]:
            raise self.err(key, f"must be [lo, hi] with lo < hi, got {v!r}")
        return float(v[0]), float(v[1])

    def strings(self, v: Any, key: str) -> tuple[str, ...]:
        if not isinstance(v, list) or not all(isinstance(x, str) and x for x in v):
            raise self.err(key, f"must be a list of names, got {v!r}")
        if len(set(v)) != len(v):
            raise self.err(key, f"names repeat: {v!r}")
        return tuple(v)

    def model_names(self, model_path: Path) -> MjcfNames:
        try:
            return read_names(model_path)
        except FileNotFoundError as exc:
            raise self.err("machine.model", f"model file not found: {exc.filename}") from None
        except (OSError, ET.ParseError, ValueError) as exc:
            raise InputError(f"cannot read the MJCF model ({exc})", file=str(model_path)) from None

    def site(self, name: str, key: str) -> str:
        if name not in self.names.sites:
            raise self.err(key, f"{name!r} is not a site of {self.model.name} (sites: {', '.join(self.names.sites)})")
        return name

    # ------------------------------------------------------------------ sections
    def spec(self) -> MachineSpec:
        mach = self.table("machine")
        name = self.text(mach, "name", "machine", default=self.folder.name)
        title = mach.get("title", "")
        if not isinstance(title, str):
            raise self.err("machine.title", f"must be a string, got {title!r}")
        self.one_line(title, "machine.title")
        kind = self.text(mach, "kind", "machine", default="chain" if "motors" in self.doc else "legacy",
                         choices=("chain",) + LEGACY_KINDS + (("legacy",) if "kind" not in mach else ()))
        model_name = self.text(mach, "model", "machine", default=f"{name}.xml")
        self.model = self.folder / model_name
        if kind != "chain":                                  # the seeded machines' own TOML
            if not self.model.is_file():
                raise self.err("machine.model", f"model file not found: {self.model}")
            return MachineSpec(name=name, folder=self.folder, model_path=self.model, title=title, legacy=True,
                               kind=kind if kind in LEGACY_KINDS else name)
        if not self.model.is_file():
            raise self.err("machine.model", f"model file not found: {self.model} (write the MJCF file name, "
                                            f"relative to the folder)")
        self.names = self.model_names(self.model)
        self.known(self.doc, "", ("machine", "motors", "tracker", "task", "workspace", "errors", "table",
                                  "closures", "names") + RECORD_SECTIONS)
        self.known(mach, "machine", ("kind", "name", "title", "model", "home"))
        home = self.text(mach, "home", "machine", default="home")
        if "home" not in mach and home not in self.names.keyframes:
            home = None                      # the default configuration (the twin checks that it closes)
        elif home not in self.names.keyframes:
            raise self.err("machine.home", f"{self.model.name} has no keyframe {home!r} (keyframes: "
                                           f"{', '.join(self.names.keyframes) or 'none'}): add an assembled "
                                           f"<key name=\"{home}\" qpos=...>")
        motors = self.motors()
        tracker = self.table("tracker")
        targets = self.strings(tracker.get("targets"), "tracker.targets")
        if not targets:
            raise self.err("tracker.targets", "needs at least one site")
        for k, t in enumerate(targets):
            self.site(t, f"tracker.targets[{k + 1}]")
        measure = self.text(tracker, "measure", "tracker", default="position", choices=MEASURES)
        if measure == "pose" and len(targets) < 3:
            raise self.err("tracker.measure", f"'pose' needs at least 3 targets, got {len(targets)}")
        if measure == "distance" and len(targets) != 2:
            raise self.err("tracker.targets", f"'distance' measures between exactly 2 sites (the scale's two "
                                              f"ends), got {len(targets)}")
        if "reference" in tracker and measure != "distance":
            raise self.err("tracker.reference", "only a 'distance' measurement has a reference pose")
        reference = self.text(tracker, "reference", "tracker", default="previous", choices=DISTANCE_REFERENCES)
        sigma = self.number(tracker, "sigma_mm", "tracker", positive=True, high=(NOISE_MAX_MM, NOISE_MAX_WHY))
        self.known(tracker, "tracker", ("targets", "measure", "sigma_mm", "reference"))
        task = self.task()
        if len(task.coordinates) > len(motors):
            raise self.err("task.coordinates", f"{len(task.coordinates)} coordinates for {len(motors)} motors: "
                                               f"the motors move the task site with {len(motors)} degrees of "
                                               f"freedom, so a target of {len(task.coordinates)} coordinates is "
                                               f"met only by chance; list the {len(motors)} (or fewer) that the "
                                               f"motors set (docs/machine_toml.md, [task])")
        workspace = self.workspace(task)
        table_axes = self.table_axes(task)
        table = self.table_grid(table_axes, workspace)
        return MachineSpec(name=name, folder=self.folder, model_path=self.model, title=title, motors=motors,
                           targets=targets, measure=measure, reference=reference, names=self.names_map(motors),
                           task=task, workspace=workspace,
                           errors=self.errors(motors), sigma_mm=sigma, table_axes=table_axes, table=table, home=home,
                           closures=self.closures(), legacy=False, kind="chain")

    def names_map(self, motors: tuple[MotorSpec, ...]) -> Mapping[str, tuple[str, ...]]:
        """``[names]``: name -> frame-error key or list of keys (each a ``<frame>.<component>`` of a body or
        site of the model, or ``mK.dzero``); the keys' existence under ``[errors]`` is the twin's check."""
        tab = self.table("names", required=False)
        out = {}
        for name, v in tab.items():
            keys = self.strings([v] if isinstance(v, str) else v, f"names.{name}")
            if not keys:
                raise self.err(f"names.{name}", "needs at least one frame-error key")
            for k in keys:
                frame, _, comp = k.rpartition(".")
                motor = {f"m{i}" for i in range(1, len(motors) + 1)}
                if frame in motor and comp == "dzero":
                    continue
                if comp not in ERROR_COMPONENTS or frame not in set(self.names.bodies) | set(self.names.sites):
                    raise self.err(f"names.{name}", f"{k!r} is not a frame error (<body or site>.<dx|dy|dz|drx|"
                                                    f"dry|drz> or mK.dzero; docs/machine_toml.md)")
            out[name] = keys
        return MappingProxyType(out)

    def closures(self) -> ClosureSpec | None:
        tab = self.table("closures", required=False)
        if not tab:
            return None
        self.known(tab, "closures", ("default_n_per_mm", "stiffness", "joint_springs"))
        default = self.number(tab, "default_n_per_mm", "closures", default=1.0, positive=True)
        per = tab.get("stiffness", {})
        if not isinstance(per, dict):
            raise self.err("closures.stiffness", "must be a table {closure name = N/mm}")
        out = {}
        for name in per:
            if name not in self.names.equalities:
                raise self.err(f"closures.stiffness.{name}", f"{name!r} is not an equality of {self.model.name} "
                                                              f"(equalities: {', '.join(self.names.equalities)})")
            out[name] = self.number(per, name, "closures.stiffness", positive=True)
        springs = tab.get("joint_springs", False)
        if not isinstance(springs, bool):
            raise self.err("closures.joint_springs", f"must be true or false, got {springs!r}")
        return ClosureSpec(default_n_per_mm=default, stiffness=MappingProxyType(out), joint_springs=springs)

    def motors(self) -> tuple[MotorSpec, ...]:
        rows = self.doc.get("motors")
        if not isinstance(rows, list) or not rows or not all(isinstance(r, dict) for r in rows):
            raise self.err("[[motors]]", "needs one [[motors]] table per actuated joint")
        out, seen = [], {}                  # joint -> its motor's number
        for i, row in enumerate(rows, start=1):
            where = f"motors[{i}]"
            joint = self.text(row, "joint", where)
            if joint not in self.names.joints:
                raise self.err(f"{where}.joint", f"{joint!r} is not a joint of {self.model.name} "
                                                 f"(joints: {', '.join(self.names.joints) or 'none'})")
            if joint in seen:
                raise self.err(f"{where}.joint", f"{joint!r} is already motor {seen[joint]}")
            seen[joint] = i
            jtype = self.names.joints[joint]
            default_kind = {"hinge": "revolute", "slide": "prismatic"}.get(jtype)
            kind = self.text(row, "kind", where, default=default_kind, choices=tuple(MOTOR_KINDS))
            if MOTOR_KINDS[kind][0] != jtype:
                raise self.err(f"{where}.kind", f"joint {joint!r} is a {jtype} joint in {self.model.name}; a "
                                                f"{kind} motor needs a {MOTOR_KINDS[kind][0]} joint")
            unit = MOTOR_KINDS[kind][1]
            given = row.get("unit", unit)
            if given != unit:
                raise self.err(f"{where}.unit", f"a {kind} motor's commands are in {unit!r}, got {given!r}")
            rng = self.interval(row.get("range"), f"{where}.range")
            zero = self.number(row, "zero", where, default=0.0)
            sigma = self.number(row, "sigma", where, default=0.0, high=MOTOR_SIGMA_MAX)
            if sigma < 0:
                raise self.err(f"{where}.sigma", f"must be >= 0 (a standard deviation in {unit}), got {sigma!r}")
            self.known(row, where, ("joint", "kind", "unit", "range", "zero", "sigma"))
            out.append(MotorSpec(name=f"m{i}", joint=joint, kind=kind, unit=unit, range=rng, zero=zero,
                                 sigma=sigma))
        return tuple(out)

    def task(self) -> TaskSpec:
        tab = self.table("task")
        self.known(tab, "task", ("site", "coordinates", "frame"))
        site = self.site(self.text(tab, "site", "task"), "task.site")
        frame = self.site(self.text(tab, "frame", "task"), "task.frame") if "frame" in tab else None
        coords = self.strings(tab.get("coordinates"), "task.coordinates")
        for c in coords:
            if c not in TASK_COORDINATES:
                raise self.err("task.coordinates", f"unknown coordinate {c!r} (choose from: "
                                                   f"{', '.join(TASK_COORDINATES)})")
        tilt = {"phi_deg", "theta_deg"} & set(coords)
        if tilt and (tilt != {"phi_deg", "theta_deg"} or {"rx_deg", "ry_deg", "rz_deg"} & set(coords)):
            raise self.err("task.coordinates", "phi_deg and theta_deg go together, without rx/ry/rz_deg")
        if not coords:
            raise self.err("task.coordinates", "needs at least one coordinate")
        return TaskSpec(site=site, coordinates=coords, frame=frame)

    def workspace(self, task: TaskSpec) -> Mapping[str, tuple[float, float]]:
        tab = self.table("workspace")
        out = {}
        for c in task.coordinates:
            if c not in tab:
                raise self.err(f"workspace.{c}", f"missing: every task coordinate needs a [lo, hi] box "
                                                 f"({c} = [lo, hi])")
            out[c] = self.interval(tab[c], f"workspace.{c}")
        extra = set(tab) - set(task.coordinates)
        if extra:
            raise self.err(f"workspace.{sorted(extra)[0]}", f"not a task coordinate (task.coordinates: "
                                                            f"{', '.join(task.coordinates)})")
        return MappingProxyType(out)

    def table_grid(self, axes: tuple[str, ...], workspace) -> "TableSpec | None":
        """``[table] nodes`` (per axis, default 9), one ``[lo, hi]`` per axis (default: the workspace box),
        ``max_step`` (deg or mm, default 10), ``reference`` (``controller`` default, or ``none``),
        ``max_correction`` (default 1) and ``max_correction_step`` (default 0.25), deg or mm."""
        tab = self.table("table", required=False)
        if not axes:        # a grid key would do nothing: say so rather than ignore a value the user set
            grid = next((k for k in tab if k != "axes"), None)
            if grid is not None:
                raise self.err(f"table.{grid}", "a table without axes has no grid (axes = []: offline compensation "
                                                "of target lists); name the axes or remove the key")
            return None
        nodes = tab.get("nodes", [TABLE_NODES_DEFAULT] * len(axes))
        if (not isinstance(nodes, list) or len(nodes) != len(axes)
                or any(isinstance(n, bool) or not isinstance(n, int) or n < 2 for n in nodes)):
            raise self.err("table.nodes", f"must be one integer >= 2 per table axis ({len(axes)}), got {nodes!r}")
        box = {a: self.interval(tab[a], f"table.{a}") if a in tab else workspace[a] for a in axes}
        step = self.number(tab, "max_step", "table", default=TABLE_MAX_STEP_DEFAULT, positive=True)
        reference = tab.get("reference", TABLE_REFERENCES[0])
        if reference not in TABLE_REFERENCES:
            raise self.err("table.reference", f"must be one of {', '.join(TABLE_REFERENCES)}, got {reference!r}")
        corr = self.number(tab, "max_correction", "table", default=TABLE_MAX_CORRECTION_DEFAULT, positive=True)
        corr_step = self.number(tab, "max_correction_step", "table", default=TABLE_MAX_CORRECTION_STEP_DEFAULT,
                                positive=True)
        return TableSpec(tuple(nodes), MappingProxyType(box), step, reference, corr, corr_step,
                         box_default=tuple(a for a in axes if a not in tab),
                         max_correction_default="max_correction" not in tab)

    def table_axes(self, task: TaskSpec) -> tuple[str, ...]:
        tab = self.table("table", required=False)
        self.known(tab, "table", ("axes", "nodes", "max_step", "reference", "max_correction", "max_correction_step")
                   + tuple(task.coordinates))
        axes = self.strings(tab.get("axes", []), "table.axes")
        if len(axes) > 3:
            raise self.err("table.axes", f"a compensation table has at most 3 axes, got {len(axes)}; leave it "
                                         f"empty for offline compensation of target lists")
        for a in axes:
            if a not in task.coordinates:
                raise self.err("table.axes", f"{a!r} is not a task coordinate ({', '.join(task.coordinates)})")
        return axes

    def errors(self, motors: tuple[MotorSpec, ...]) -> ErrorSpec:
        tab = self.table("errors", required=False)
        frames = tab.get("frames", "all")
        known = set(self.names.bodies) | set(self.names.sites)
        if frames != "all":
            frames = self.strings(frames, "errors.frames")
            for f in frames:
                if f not in known:
                    raise self.err("errors.frames", f"{f!r} is neither a body nor a site of {self.model.name}")
        exclude = self.strings(tab.get("exclude", []), "errors.exclude")
        for f in exclude:
            if f not in known:
                raise self.err("errors.exclude", f"{f!r} is neither a body nor a site of {self.model.name}")
        comps = self.strings(tab.get("components", list(ERROR_COMPONENTS)), "errors.components")
        for c in comps:
            if c not in ERROR_COMPONENTS:
                raise self.err("errors.components", f"unknown component {c!r} (choose from: "
                                                    f"{', '.join(ERROR_COMPONENTS)})")
        mz = tab.get("motor_zero", True)
        if not isinstance(mz, bool):
            raise self.err("errors.motor_zero", f"must be true or false, got {mz!r}")
        sizes = {k: self.number(tab, k, "errors", default=d, positive=True, high=ERROR_SIZE_MAX[k.rsplit("_", 1)[1]])
                 for k, d in (("position_mm", 1.0), ("angle_deg", 0.3), ("zero_deg", 1.0), ("zero_mm", 1.0))}
        self.known(tab, "errors", ("frames", "exclude", "components", "motor_zero", *sizes))
        return ErrorSpec(frames=frames, exclude=exclude, components=comps, motor_zero=mz, **sizes)
