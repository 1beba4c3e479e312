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
    bodies, sites, keyframes, equalities : declared names, in file order.
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


def read_names(path: Path) -> MjcfNames:
    """Joints (with type), bodies, sites and keyframes of the MJCF file ``path`` (see module docstring).

    Raises ``OSError`` if a file cannot be read and ``xml.etree.ElementTree.ParseError`` or ``ValueError``
    if it is not well-formed MJCF; the caller turns those into an input error naming the file.
    """
    root = _expand(Path(path), set())
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
    for eq in root.findall("equality"):
        out.equalities += [e.get("name") for e in eq if e.get("name")]
    for kf in root.findall("keyframe"):
        out.keyframes += [k.get("name") for k in kf.findall("key") if k.get("name")]
    return out
