"""The calibrated machine as MJCF: the machine's model file with a compiled model's geometry written in.

The twins insert errors by compiled-model edits (:func:`pmcal.twin.ocpm.model.apply_errors`,
:class:`pmcal.twin.frame_errors.FrameErrors`): the compiled model holds the real machine's frames. This
module copies them back into the machine's own MJCF text, so the exported file is the familiar model
(classes, materials, comments, actuators kept) with only numbers changed:

- every named ``body``: ``pos`` and ``quat`` (``euler``/``axisangle``/``xyaxes``/``zaxis`` removed);
- every named ``site``: ``pos`` and ``quat``; every named ``joint``: ``pos`` and ``axis``;
- optional joint ``ref`` values, actuator gains, joint stiffness, a keyframe, ``custom`` numerics and a
  header comment.

Numbers are written with Python's shortest round-trip repr (17 significant digits when needed): MjSpec's
own ``to_xml`` keeps 6, which moves a 0.4 m body by up to 5e-7 m. Units: whatever the template uses (SI
lengths; ``ref`` converted to the template's ``compiler angle``). Visual geoms keep their nominal shapes.
"""

from __future__ import annotations

import math
import os
import xml.etree.ElementTree as ET
from pathlib import Path

import mujoco
import numpy as np

from pmcal.twin.closures import sites_for_body_closures

#: What the machine.toml export-model writes beside a calibrated MJCF starts with (its twin knows the model is
#: an identified machine by it, the exports written before ``pmcal_identified_machine`` included)
CALIBRATED_TOML_START = "# Calibrated "

#: attributes that give an element's orientation besides ``quat`` (removed when ``quat`` is written)
ORIENTATIONS = ("euler", "axisangle", "xyaxes", "zaxis")


def numbers(values) -> str:
    """Space-separated shortest round-trip representation of floats."""
    return " ".join(repr(float(v)) for v in np.ravel(values))


def _parse(path: Path) -> ET.ElementTree:
    parser = ET.XMLParser(target=ET.TreeBuilder(insert_comments=True))
    return ET.parse(str(path), parser)


#: asset elements whose ``file`` MuJoCo resolves against ``compiler meshdir`` (else ``assetdir``), and
#: those it resolves against ``texturedir`` (else ``assetdir``)
MESH_ASSETS, TEXTURE_ASSETS = ("mesh", "hfield", "skin"), ("texture",)
#: ``compiler`` attributes that locate asset files; the exported file writes each path in full instead
ASSET_DIRS = ("meshdir", "texturedir", "assetdir")
#: texture attributes that name files besides ``file`` (cube and skybox faces)
TEXTURE_FILES = ("fileright", "fileleft", "fileup", "filedown", "filefront", "fileback")


def relocate_assets(root: ET.Element, path: Path, output: Path) -> None:
    """Rewrite, in the MJCF document ``root`` read from ``path``, every asset file path (meshes, textures,
    height fields, skins; ``compiler meshdir``/``texturedir``/``assetdir`` honoured, as MuJoCo resolves
    them) relative to the folder of ``output``, where the document will be written, and drop those compiler
    directories: the exported model loads the machine's own mesh files wherever it is written. ValueError
    naming the element and the file when an asset is missing or the template includes other MJCF files
    (their bodies would not carry the calibration)."""
    comp = root.find("compiler")
    dirs = {k: (comp.get(k) if comp is not None else None) for k in ASSET_DIRS}
    here = path.resolve().parent
    target = output.resolve().parent

    def base(kind: str) -> Path:
        d = dirs["texturedir" if kind in TEXTURE_ASSETS else "meshdir"] or dirs["assetdir"] or ""
        return here / d

    for el in root.iter():
        if el.tag == "include":
            raise ValueError(f"{path}: <include file={el.get('file')!r}> : the exporter writes the calibrated "
                             "frames into one file; merge the included MJCF into the model first")
        names = [a for a in ("file",) + TEXTURE_FILES if a in el.attrib]
        if not names:
            continue
        if el.tag not in MESH_ASSETS + TEXTURE_ASSETS:
            raise ValueError(f"{path}: <{el.tag} file=...> is not an asset the exporter can relocate")
        for a in names:
            src = base(el.tag) / el.get(a)
            if not src.is_file():
                raise ValueError(f"{path}: <{el.tag} {a}={el.get(a)!r}>: file not found: {src}")
            el.set(a, Path(os.path.relpath(src.resolve(), target)).as_posix())
    if comp is not None:
        for k in ASSET_DIRS:
            comp.attrib.pop(k, None)


def _angle_scale(root: ET.Element) -> float:
    """Template units per radian (MJCF's default compiler angle is degrees)."""
    comp = root.find("compiler")
    angle = comp.get("angle", "degree") if comp is not None else "degree"
    return 1.0 if angle == "radian" else 180.0 / math.pi


def calibrated_xml(template: str | Path, model: mujoco.MjModel, *, header: list[str] = (),
                   joint_ref: dict[str, float] | None = None, actuator_kp: dict[str, float] | None = None,
                   joint_stiffness: dict[str, float] | None = None, keyframe: tuple[str, np.ndarray, np.ndarray] | None = None,
                   custom: dict[str, list[float]] | None = None, option: dict[str, str] | None = None,
                   equality_active: dict[str, bool] | None = None, output: str | Path | None = None) -> str:
    """MJCF text of ``template`` with ``model``'s body, site and joint frames written in.

    Parameters
    ----------
    template : path
        The machine's MJCF file (the one ``model`` was compiled from, before the edits).
    model : mujoco.MjModel
        The compiled real machine (SI); elements are matched by name.
    header : list of str
        Lines of the comment written before ``<mujoco>``.
    joint_ref : dict, optional
        Joint name -> ``ref`` in SI: rad for a hinge (written in the template's angle unit), m for a slide.
    actuator_kp : dict, optional
        Position actuator name -> ``kp`` (N m/rad for a hinge).
    joint_stiffness : dict, optional
        Joint name -> ``stiffness`` (N/m for a slide, N m/rad for a hinge).
    keyframe : (name, qpos, ctrl), optional
        Replace (or add) the keyframe ``name``.
    custom : dict, optional
        ``<custom><numeric name=... data=...>`` entries.
    option : dict, optional
        Attributes of ``<option>`` (e.g. ``integrator``, ``timestep``).
    equality_active : dict, optional
        Equality constraint name -> active.
    output : path, optional
        Where the document will be written: asset file paths (meshes, textures) are rewritten relative to its
        folder (:func:`relocate_assets`). Default: the template's folder.

    Returns
    -------
    str
        The MJCF document.

    Examples
    --------
    >>> m = mujoco.MjModel.from_xml_path("mjcf/ocpm_2dof/ocpm_2dof.xml")     # doctest: +SKIP
    >>> text = calibrated_xml("mjcf/ocpm_2dof/ocpm_2dof.xml", m)             # doctest: +SKIP
    """
    path = Path(template)
    tree = _parse(path)
    root = tree.getroot()
    relocate_assets(root, path, Path(output) if output is not None else path)
    obj = mujoco.mjtObj

    def ident(kind, name):
        i = mujoco.mj_name2id(model, kind, name)
        if i < 0:
            raise ValueError(f"{path}: {name!r} is not in the compiled model")
        return i

    sites_for_body_closures(root, model)          # body-based closures as the twin holds them
    world = root.find("worldbody")
    in_frame = _enclosing_frames(root, world)
    for el in world.iter():
        name = el.get("name")
        if not name or el.tag not in ("body", "site", "joint"):
            continue
        # compiled values are in the parent body's frame; inside <frame> elements they are written in the
        # innermost frame's (MuJoCo folds frames into their children at compile time)
        to_local = in_frame.get(id(el), _IDENTITY)
        if el.tag == "body":
            i = ident(obj.mjOBJ_BODY, name)
            pos, quat = to_local(model.body_pos[i], model.body_quat[i])
            el.set("pos", numbers(pos))
            for a in ORIENTATIONS:
                el.attrib.pop(a, None)
            el.set("quat", numbers(quat))
        elif el.tag == "site":
            if "fromto" in el.attrib:
                raise ValueError(f"{path}: site {name!r} uses fromto; not supported by the exporter")
            i = ident(obj.mjOBJ_SITE, name)
            pos, quat = to_local(model.site_pos[i], model.site_quat[i])
            el.set("pos", numbers(pos))
            if any(a in el.attrib for a in ORIENTATIONS + ("quat",)) or not np.allclose(quat, [1, 0, 0, 0]):
                for a in ORIENTATIONS:
                    el.attrib.pop(a, None)
                el.set("quat", numbers(quat))
        else:
            i = ident(obj.mjOBJ_JOINT, name)
            if model.jnt_type[i] != mujoco.mjtJoint.mjJNT_FREE:
                pos, _ = to_local(model.jnt_pos[i], None)
                el.set("pos", numbers(pos))
                if model.jnt_type[i] in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE):
                    el.set("axis", numbers(to_local.rotate(model.jnt_axis[i])))
    scale = _angle_scale(root)
    joints = {el.get("name"): el for el in world.iter("joint") if el.get("name")}
    for name, ref in (joint_ref or {}).items():
        hinge = model.jnt_type[ident(obj.mjOBJ_JOINT, name)] == mujoco.mjtJoint.mjJNT_HINGE
        joints[name].set("ref", repr(float(ref) * (scale if hinge else 1.0)))
    for name, k in (joint_stiffness or {}).items():
        joints[name].set("stiffness", repr(float(k)))
    acts = {el.get("name"): el for el in root.iter() if el.get("name") and el.tag in ("position", "general")}
    for name, kp in (actuator_kp or {}).items():
        el = acts[name]
        if el.tag != "position":
            raise ValueError(f"{path}: actuator {name!r} is not a <position> actuator")
        el.set("kp", repr(float(kp)))
    if option:
        opt = root.find("option")
        if opt is None:
            opt = ET.Element("option")
            root.insert(0, opt)
        for k, v in option.items():
            opt.set(k, str(v))
    eqs = {el.get("name"): el for el in (root.find("equality") if root.find("equality") is not None else [])}
    for name, active in (equality_active or {}).items():
        eqs[name].set("active", "true" if active else "false")
    if keyframe is not None:
        kname, qpos, ctrl = keyframe
        kf = root.find("keyframe")
        if kf is None:
            kf = ET.SubElement(root, "keyframe")
        key = next((k for k in kf.iter("key") if k.get("name") == kname), None)
        if key is None:
            key = ET.SubElement(kf, "key", name=kname)
        key.set("qpos", numbers(qpos))
        key.set("ctrl", numbers(ctrl))
    if custom:
        cu = root.find("custom")
        if cu is None:
            cu = ET.Element("custom")
            root.insert(_index_before(root, ("worldbody", "asset")), cu)
        for name, data in custom.items():          # a numeric of the template's own (a re-export): replaced
            num = next((n for n in cu.iter("numeric") if n.get("name") == name), None)
            if num is None:
                num = ET.SubElement(cu, "numeric", name=name)
            num.set("data", numbers(data))
    ET.indent(tree, space="  ")
    body = ET.tostring(root, encoding="unicode")
    text = "\n".join(line.replace("--", "- -") for line in header)
    raw = path.read_text(encoding="utf-8")
    leading = raw[:raw.find("<mujoco")].strip()           # the template's own opening comment, kept
    return (f"<!--\n{text}\n-->\n" if header else "") + (leading + "\n" if leading.startswith("<!--") else "") \
        + body + "\n"


class _FrameTransform:
    """Pose ``(p, q)`` of a ``<frame>`` in its parent body (SI, quaternion w-first): maps a compiled
    (parent-body) position and orientation into the frame's own coordinates."""

    def __init__(self, p: np.ndarray, q: np.ndarray):
        self.p, self.q = np.asarray(p, float), np.asarray(q, float)
        self.R = np.zeros(9)
        mujoco.mju_quat2Mat(self.R, self.q)
        self.R = self.R.reshape(3, 3)

    def rotate(self, v: np.ndarray) -> np.ndarray:
        return self.R.T @ np.asarray(v, float)

    def __call__(self, pos, quat):
        local = self.R.T @ (np.asarray(pos, float) - self.p)
        if quat is None:
            return local, None
        qi, out = np.zeros(4), np.zeros(4)
        mujoco.mju_negQuat(qi, self.q)
        mujoco.mju_mulQuat(out, qi, np.asarray(quat, float))
        return local, out


_IDENTITY = _FrameTransform(np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]))
_PROBE = "__pmcal_frame_probe_"


def _enclosing_frames(root: ET.Element, world: ET.Element) -> dict[int, _FrameTransform]:
    """``id(element) -> transform`` of the innermost ``<frame>`` enclosing each body, site and joint that
    sits in one (below its parent body). The frames' poses are MuJoCo's own: a copy of the document with a
    bare site as the first child of every frame is compiled, and each site's compiled pose is its frame's
    (nested frames composed, every orientation form and ``compiler`` setting honoured)."""
    frames = list(world.iter("frame"))
    if not frames:
        return {}
    parent = {child: el for el in world.iter() for child in el}
    probe = ET.fromstring(ET.tostring(root))
    for k, fr in enumerate(probe.find("worldbody").iter("frame")):
        fr.insert(0, ET.Element("site", name=f"{_PROBE}{k}", pos="0 0 0", quat="1 0 0 0"))
    m = mujoco.MjModel.from_xml_string(ET.tostring(probe, encoding="unicode"))
    pose = {}
    for k, fr in enumerate(frames):
        i = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, f"{_PROBE}{k}")
        pose[id(fr)] = _FrameTransform(m.site_pos[i].copy(), m.site_quat[i].copy())
    out = {}
    for el in world.iter():
        if el.tag not in ("body", "site", "joint"):
            continue
        up = parent.get(el)                     # a frame parent is the innermost one
        if up is not None and up.tag == "frame":
            out[id(el)] = pose[id(up)]
    return out


def _index_before(root: ET.Element, tags: tuple[str, ...]) -> int:
    for i, el in enumerate(root):
        if el.tag in tags:
            return i
    return len(root)


def simulate(path: str | Path, steps: int = 500, keyframe: str | None = "home") -> tuple[mujoco.MjModel, mujoco.MjData]:
    """Load an MJCF file and step it ``steps`` times from ``keyframe`` (the default pose if None), the
    controls held at the keyframe's. Returns the model and the data (``data.warning`` counts MuJoCo's
    warnings)."""
    m = mujoco.MjModel.from_xml_path(str(path))
    d = mujoco.MjData(m)
    if keyframe is not None:
        mujoco.mj_resetDataKeyframe(m, d, mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, keyframe))
    for _ in range(steps):
        mujoco.mj_step(m, d)
    return m, d
