"""``pmcal export-model``: the calibrated machine as a MuJoCo model (MJCF) and a machine.toml beside it.

Where each identified quantity goes (docs/formats.md, "Calibrated model"):

- geometry (every ``L<j>.*`` and ``SS.*`` key; planar: ``de*``, ``dL*``, ``dl*``, ``drM*``): body, site and
  joint frames of the machine's MJCF, as the twin inserts them (:func:`pmcal.twin.export.calibrated_xml`);
- nest offsets of a tracker-frame calibration: the target sites ``T1``..;
- motor zero offsets (``ocpm_2dof`` ``L1.dtheta``, ``L2.dtheta``; ``planar_2dof`` ``dtheta1``, ``dtheta2``):
  the motor joints' ``ref = -dtheta``, so the joint coordinate (and the position servo's control) is the
  commanded angle while the link sits ``dtheta`` further on;
- closure stiffness ratio (``ocpm_2dof``): ``custom`` numerics ``pmcal_stiffness_ratio`` and
  ``pmcal_passive_closure_stiffness`` (N/m) and the machine.toml; MuJoCo's soft constraints have no
  stiffness in N/m, so the exported model simulates like the dynamic twin (:data:`SIMULATION_OPTIONS`,
  closures hard, the SS limb's axial spring locked), while the quasi-static assembly of the twin reads
  the ratio from the numerics and reproduces the identified model;
- effects named by ``diagnose``: ``joint_compliance`` K as the motors' position-servo gain ``kp`` (a
  servo of gain K is the torsional spring K in series between command and joint; a joint ``stiffness``
  would pull towards a fixed ``springref`` instead), ``backlash`` as a comment and in the machine.toml;
  those MJCF cannot hold (thermal expansion, zero-offset drift, encoder eccentricity, over-constraint)
  are listed in the comment and the machine.toml.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import mujoco
import numpy as np

from pmcal.errors import InputError, RunError
from pmcal.fileio import atomic_write, check_output
from pmcal.io_chain import read_params as read_chain_params
from pmcal.twin.closed_chain import IDENTIFIED_NUMERIC, REDUNDANT_NUMERIC
from pmcal.twin.export import CALIBRATED_TOML_START, calibrated_xml

#: What the machine.toml written beside a calibrated MJCF starts with: an existing file of that name is
#: replaced only if it is one
SIDE_FILE_START = CALIBRATED_TOML_START

#: effects written as a comment and in the machine.toml only
AS_COMMENT = {"backlash": "full dead band of lost motion per motor (deg), as diagnose reports it: 2b in "
                          "joint = command + dtheta - b * approach sign"}


@dataclass
class ExportParts:
    """What a machine's calibration puts into its exported model (each machine's code builds it:
    :func:`chain_parts`, ``pmcal.ocpm.calibration.export_parts``, ``pmcal.planar.calibration.export_parts``).

    ``template``: the machine's MJCF; ``toml_path``: its machine.toml; ``model``: the compiled model with the
    identified errors; ``edits``: the MJCF edits :func:`pmcal.twin.export.calibrated_xml` applies (joint refs,
    keyframe, options, custom numerics); ``params``, ``doc``: the parameters and their document; ``facts``:
    what the header and the machine.toml say (``machine``, ``model``, zero offsets and how they are held);
    ``holds``: the named effects this machine's MJCF can hold and where; ``effect_edits(effects)``: the edits
    that put them there."""

    template: Path
    toml_path: Path
    model: mujoco.MjModel
    edits: dict
    params: dict
    doc: dict
    facts: dict
    holds: dict = field(default_factory=dict)
    effect_edits: Callable[[dict], dict] | None = None


def _toml_value(v) -> str:
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (list, tuple, np.ndarray)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return repr(float(v))


def toml_text(sections: dict[str, dict]) -> str:
    """A TOML document of flat sections (str, number, list values)."""
    out = []
    for name, items in sections.items():
        out.append(f"[{name}]")
        out += [f'"{k}" = {_toml_value(v)}' if not k.replace("_", "").isalnum() else f"{k} = {_toml_value(v)}"
                for k, v in items.items()]
        out.append("")
    return "\n".join(out)


def read_effects(doc: dict, path: str) -> dict[str, dict]:
    """Named effects of a parameters file (``diagnose --report DIR`` writes ``params.json`` with an
    ``effects`` object: name -> {value, interval, unit, params}); {} when there is none."""
    effects = doc.get("effects") or {}
    if not isinstance(effects, dict):
        raise InputError("'effects' must be an object of effect name -> {value, unit}", file=path, field="effects")
    out = {}
    for name, e in effects.items():
        e = e if isinstance(e, dict) else {"value": e}
        value = e.get("value")
        vals = value if isinstance(value, list) else [value]
        if not vals or any(isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v)
                           for v in vals):
            raise InputError(f"effect value {value!r} is not a finite number", file=path, field=f"effects.{name}")
        out[name] = {"value": value, "unit": e.get("unit", ""), "interval": e.get("interval")}
    return out


def frame_parts(twin, spec, params: dict):
    """The compiled model with the frame errors ``params`` and the MJCF edits that carry the rest: motor zero
    offsets as the motor joints' ``ref`` (joint coordinate = command - zero, as in the nominal model, while
    the link sits ``dzero`` further on), the home keyframe re-assembled."""
    twin.set_params(params)
    qpos = twin.solve(twin.home_commands[None], params)[0]
    if not np.isfinite(qpos).all():
        raise RunError("the calibrated machine does not assemble at the home keyframe's commands")
    m = twin.model
    shift = twin.errors.zero_offset * twin.motor_unit                  # SI, per motor
    qpos[twin.motor_qadr] -= shift
    refs = {mot.joint: float(m.qpos0[a] - d) for mot, a, d in zip(spec.motors, twin.motor_qadr, shift) if d}
    # an over-constrained loop: which equations the joints' play takes up stays the design's (the twin of the
    # exported model reads it back instead of finding it at its own, error-tilted home)
    custom = {REDUNDANT_NUMERIC: twin.redundant_directions.ravel()} if len(twin.redundant_directions) else {}
    custom[IDENTIFIED_NUMERIC] = np.ones(1)               # the identified machine, not a drawing (its twin's checks)
    if spec.home is None:                       # the default configuration: written as a 'home' keyframe
        keyframe = ("home", qpos, np.zeros(m.nu))
    else:
        keyframe = (spec.home, qpos, m.key_ctrl[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, spec.home)].copy())
    return m, dict(joint_ref=refs, keyframe=keyframe, custom=custom)


def chain_parts(params_path: str, machine) -> ExportParts:
    """A machine folder's calibration (``pmcal --machine DIR identify``): the twin's frames with the
    identified errors (:func:`frame_parts`)."""
    twin, spec = machine.twin, machine.spec
    params, doc = read_chain_params(params_path, spec, dict(zip(twin.error_keys, twin.error_units())))
    m, edits = frame_parts(twin, spec, params)
    zero = [f"{v:.6g} {mot.unit}" for mot, v in zip(spec.motors, twin.errors.zero_offset)]
    facts = {"machine": spec.name, "model": "chain", "zero_offsets": zero,
             "zero_offsets_as": "motor joints' ref lowered by dzero: joint coordinate = command - zero"}
    return ExportParts(spec.model_path, spec.folder / "machine.toml", m, edits, params, doc, facts)


def _zero_text(facts: dict) -> str:
    if "zero_offsets_deg" in facts:
        return ", ".join(f"{v:.6g}" for v in facts["zero_offsets_deg"]) + " deg"
    return ", ".join(facts["zero_offsets"])


def _retarget_model(toml: str, model_name: str) -> str:
    """The machine.toml text with ``[machine] model`` naming ``model_name`` (the key added if absent)."""
    lines = toml.splitlines()
    start = next(i for i, line in enumerate(lines) if line.strip() == "[machine]")
    end = next((i for i in range(start + 1, len(lines)) if lines[i].lstrip().startswith("[")), len(lines))
    for i in range(start + 1, end):
        if re.match(r"\s*model\s*=", lines[i]):
            lines[i] = f'model = "{model_name}"'
            break
    else:
        lines.insert(start + 1, f'model = "{model_name}"')
    return "\n".join(lines) + "\n"


def export_model(parts: ExportParts, params_path: str | Path, output: str | Path, keep=None) -> dict:
    """Write the calibrated MJCF (``output``) and its machine.toml (``output`` with suffix ``.toml``).

    Parameters
    ----------
    parts : ExportParts
        The machine's calibration as its exported model holds it (:class:`ExportParts`).
    params_path : path
        Parameters JSON of ``pmcal identify`` (or ``params.json`` of ``diagnose --report``, which adds the
        named effects): named in the header.
    output : path
        MJCF file to write. Mesh and texture files stay where they are: their paths are rewritten relative to
        the output's folder (``compiler meshdir``/``texturedir``/``assetdir`` honoured); a missing asset or
        an ``<include>`` is an InputError (exit 2).
    keep : path, optional
        The machine folder: never written into.

    Returns
    -------
    dict
        ``in_mjcf`` (effect -> where), ``comment_only`` and ``not_in_mjcf`` (effect names), ``toml`` (path).

    Examples
    --------
    >>> export_model(chain_parts("params.json", machine), "params.json", "calibrated.xml")   # doctest: +SKIP
    >>> import mujoco; mujoco.MjModel.from_xml_path("calibrated.xml")                        # doctest: +SKIP
    """
    params_path = str(params_path)
    template, toml_path, model, edits, params, doc, facts = (parts.template, parts.toml_path, parts.model,
                                                             dict(parts.edits), parts.params, parts.doc, parts.facts)
    effects = read_effects(doc, params_path)
    in_mjcf = {n: parts.holds[n] for n in effects if n in parts.holds}
    comment_only = [n for n in effects if n in AS_COMMENT]
    not_in = [n for n in effects if n not in in_mjcf and n not in comment_only]
    if in_mjcf and parts.effect_edits is not None:
        edits.update(parts.effect_edits({n: effects[n] for n in in_mjcf}))
    stamp = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    header = [f" Calibrated {facts['machine']}: written by pmcal export-model from {params_path} ({stamp}).",
              f" The machine's MJCF ({template.name}) with the identified geometry in the body, joint and site "
              "frames (SI units).",
              f" Zero offsets {_zero_text(facts)}: {facts['zero_offsets_as']}."]
    if "stiffness_ratio" in facts:
        header.append(f" Closure stiffness ratio {facts['stiffness_ratio']:.6g} (quasi-static assembly): custom numerics "
                      "pmcal_stiffness_ratio, pmcal_passive_closure_stiffness (N/m). For simulation the closures are "
                      "hard and the SS axial spring locked (Euler, 0.2 ms), as pmcal's dynamic twin.")
    header += [f" Effect {n} = {effects[n]['value']} {effects[n]['unit']}: {w}." for n, w in in_mjcf.items()]
    header += [f" Effect {n} = {effects[n]['value']} {effects[n]['unit']}: not representable in MJCF ({AS_COMMENT[n]});"
               f" in {Path(output).with_suffix('.toml').name}." for n in comment_only]
    header += [f" Effect {n} = {effects[n]['value']} {effects[n]['unit']}: not representable in MJCF; listed in "
               f"{Path(output).with_suffix('.toml').name}." for n in not_in]
    try:
        text = calibrated_xml(template, model, header=header, output=output, **edits)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    nominal = _retarget_model(toml_path.read_text(encoding="utf-8"), Path(output).name)
    extra = {"calibration": {"source": params_path, "written": stamp, "mjcf": Path(output).name,
                             **{k: v for k, v in facts.items() if k != "machine"}},
             "calibration.params": {k: float(v) for k, v in params.items()}}
    for n, e in effects.items():
        where = in_mjcf.get(n) or ("comment and this file" if n in comment_only else "not representable in MJCF")
        extra[f"effects.{n}"] = {"value": e["value"], "unit": e["unit"], "in_mjcf": where,
                                 **({"interval": e["interval"]} if e.get("interval") else {})}
    toml_out = Path(output).with_suffix(".toml")
    check_output(output, suffixes=(".xml",), machine_folder=keep)
    check_output(toml_out, machine_folder=keep, own=SIDE_FILE_START)
    toml = (f"{SIDE_FILE_START}{facts['machine']} (pmcal export-model, {stamp}): the nominal machine.toml and the\n"
            "# calibration below it. Units: mm, degrees (the MJCF itself is SI).\n" + nominal.rstrip() + "\n\n"
            + toml_text(extra))                  # both texts before either file: none written alone
    with atomic_write(output) as fh:
        fh.write(text)
    with atomic_write(toml_out) as fh:
        fh.write(toml)
    return {"in_mjcf": in_mjcf, "comment_only": comment_only, "not_in_mjcf": not_in, "toml": str(toml_out)}
