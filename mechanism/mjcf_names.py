"""The names an MJCF file declares (joints with their types, bodies, sites, keyframes), read without MuJoCo.

:mod:`pmcal.mechanism.machine_spec` checks a ``machine.toml`` against its model with this reader, so a
wrong joint or site name is reported at load, naming the file and the key, before any MuJoCo model is
compiled. It follows ``<include file=...>`` (relative to the including file) and resolves a joint's type
through the default classes (``class`` on the element, else the nearest ancestor's ``childclass``, up the
``<default>`` tree; MuJoCo's default type is ``hinge``).

Example
-------
>>> names = read_names(Path("mjcf/delta_3dof/delta_3dof.xml"))    # doctest: +SKIP
>>> names.joints["arm1_hip"]                                       # doctest: +SKIP
'hinge'
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path


@dataclass
class MjcfNames:
    """Names declared by a model file.

    joints : joint name -> type (``"hinge"``, ``"slide"``, ``"ball"``, ``"free"``).
    bodies, sites, keyframes, equalities : declared names, in file order (sites: with the two sites each
        active body-based closure is converted to, :func:`closure_site_names`).
    """

    joints: dict[str, str] = field(default_factory=dict)
    bodies: list[str] = field(default_factory=list)
    sites: list[str] = field(default_factory=list)
    keyframes: list[str] = field(default_factory=list)
    equalities: list[str] = field(default_factory=list)


def _expand(path: Path, seen: set[Path]) -> ET.Element:
    """The root element of ``path`` with every ``<include>`` replaced by the included file's children."""
    root = ET.parse(path).getroot()
    seen = seen | {path.resolve()}

    def walk(elem: ET.Element) -> None:
        for i, child in enumerate(list(elem)):
            if child.tag == "include":
                inc = (path.parent / child.get("file", "")).resolve()
                if inc in seen:
                    raise ValueError(f"{path.name} includes {inc.name} recursively")
                if not inc.is_file():     # not machine.toml's [machine] model: the include names it
                    raise ValueError(f"{path.name} includes file={child.get('file', '')!r}, which is no file ({inc})")
                sub = _expand(inc, seen)
                elem.remove(child)
                for k, grand in enumerate(list(sub)):
                    elem.insert(i + k, grand)
            else:
                walk(child)

    walk(root)
    return root


def _default_types(root: ET.Element) -> tuple[dict[str, str | None], dict[str, str | None]]:
    """Per default class: the joint type it sets (or None) and its parent class."""
    types: dict[str, str | None] = {}
    parent: dict[str, str | None] = {}

    def walk(elem: ET.Element, name: str, up: str | None) -> None:
        parent[name] = up
        joint = elem.find("joint")
        types[name] = joint.get("type") if joint is not None else None
        for child in elem.findall("default"):
            walk(child, child.get("class", "main"), name)

    for top in root.findall("default"):
        walk(top, top.get("class", "main"), None)
    return types, parent


def closure_site_names(equality: str | None, index: int) -> tuple[str, str]:
    """Names of the two sites that stand for a body-based connect/weld (``pmcal.twin.closures`` adds them
    on load): ``<equality name>_site1``/``_site2``, or ``closure<index>_site1``/``_site2`` for an unnamed
    equality, ``index`` its position among the model's equalities (from 0). A user lists them in
    ``[errors] frames`` like any site."""
    stem = equality or f"closure{index}"
    return f"{stem}_site1", f"{stem}_site2"


def read_names(path: Path) -> MjcfNames:
    """Joints (with type), bodies, sites and keyframes of the MJCF file ``path`` (see module docstring).

    Raises ``OSError`` if a file cannot be read and ``xml.etree.ElementTree.ParseError`` or ``ValueError``
    if it is not well-formed MJCF; the caller turns those into an input error naming the file.
    """
    root = _expand(Path(path), set())
    if root.tag != "mujoco":                 # an HTML page, a URDF (<robot>): every name would be 'missing'
        raise ValueError(f"its root element is <{root.tag}>, not <mujoco>: not an MJCF model")
    types, parent = _default_types(root)

    def joint_type(cls: str | None) -> str:
        while cls is not None:
            if types.get(cls):
                return str(types[cls])
            cls = parent.get(cls)
        return "hinge"

    out = MjcfNames()

    def walk(elem: ET.Element, childclass: str) -> None:
        for child in elem:
            if child.tag == "body":
                if child.get("name"):
                    out.bodies.append(child.get("name"))
                walk(child, child.get("childclass", childclass))
            elif child.tag in ("joint", "freejoint") and child.get("name"):
                kind = "free" if child.tag == "freejoint" else \
                    child.get("type") or joint_type(child.get("class", childclass))
                out.joints[child.get("name")] = kind
            elif child.tag == "site" and child.get("name"):
                out.sites.append(child.get("name"))
            elif child.tag == "frame":
                walk(child, child.get("childclass", childclass))

    for world in root.findall("worldbody"):
        walk(world, "main")
    index = 0
    for eq in root.findall("equality"):
        for e in eq:
            if not isinstance(e.tag, str):
                continue
            if e.get("name"):
                out.equalities.append(e.get("name"))
            if e.tag in ("connect", "weld") and e.get("body1") and e.get("active", "true") != "false":
                out.sites += list(closure_site_names(e.get("name"), index))      # converted on load
            index += 1
    for kf in root.findall("keyframe"):
        out.keyframes += [k.get("name") for k in kf.findall("key") if k.get("name")]
    return out
