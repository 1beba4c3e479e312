"""Loop closures as site-based equalities: body-based ``connect`` and ``weld`` converted on load.

The closed-chain twin (:mod:`pmcal.twin.closed_chain`) closes loops between two **sites**, whose positions
(and, for a weld, orientations) in their bodies are model data that geometric errors move. MuJoCo's
older body-based form (``<connect body1= body2= anchor=>``, ``<weld body1= body2= [anchor=] [relpose=]>``)
holds the same information once compiled: the anchor point in each body's frame (body2's derived by the
compiler from the reference configuration ``qpos0``), and for a weld the relative orientation. This module
turns every active body-based connect/weld into the equivalent site-based one by adding two sites,
``<equality name>_site1`` on body1 and ``_site2`` on body2 (``closureN_site1`` for an unnamed equality, N
its index), at those compiled anchors, so a model written either way is calibrated the same way and its
anchors carry errors like any closure site. Also the stacked linear solve the closure solvers share
(:func:`solve_stacked`: one Newton step per configuration of a batch).

MuJoCo's body-based residuals (``engine_core_constraint.c``): connect, the point ``eq_data[0:3]`` of body1
meets ``eq_data[3:6]`` of body2; weld, the point ``eq_data[3:6]`` of body1 meets ``eq_data[0:3]`` of
body2 and body2's orientation is body1's times ``eq_data[6:10]``. tests/test_closures.py checks the
converted model's constraint residuals against the original's.

Units: SI (the compiled model's).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import mujoco
import numpy as np

from pmcal.mechanism.mjcf_names import closure_site_names as site_names

_OBJ = mujoco.mjtObj
_EQ = mujoco.mjtEq
_IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


def closure_site_names(model: mujoco.MjModel, e: int) -> tuple[str, str]:
    """Names of the two sites that stand for the body-based closure ``e``
    (:func:`pmcal.mechanism.mjcf_names.closure_site_names`)."""
    return site_names(mujoco.mj_id2name(model, _OBJ.mjOBJ_EQUALITY, e), e)


def body_closures(model: mujoco.MjModel) -> list[int]:
    """Indices of the active body-based connect and weld equalities."""
    return [e for e in range(model.neq) if model.eq_active0[e]
            and int(model.eq_type[e]) in (_EQ.mjEQ_CONNECT, _EQ.mjEQ_WELD)
            and int(model.eq_objtype[e]) == _OBJ.mjOBJ_BODY]


def anchors(model: mujoco.MjModel, e: int) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """``((pos1, quat1), (pos2, quat2))``: the frames, in body1's and body2's coordinates, that the
    body-based closure ``e`` makes coincide (positions only for a connect)."""
    data = model.eq_data[e]
    if int(model.eq_type[e]) == _EQ.mjEQ_CONNECT:
        return (data[0:3].copy(), _IDENTITY.copy()), (data[3:6].copy(), _IDENTITY.copy())
    q = data[6:10] / np.linalg.norm(data[6:10])
    return (data[3:6].copy(), q), (data[0:3].copy(), _IDENTITY.copy())


def compile_with_site_closures(path: str | Path) -> mujoco.MjModel:
    """The compiled model of the MJCF file ``path`` with its body-based closures turned site-based (module
    docstring); the model itself when it has none. MuJoCo's ``ValueError`` if it does not compile."""
    model = mujoco.MjModel.from_xml_path(str(path))
    todo = body_closures(model)
    if not todo:
        return model
    spec = mujoco.MjSpec.from_file(str(path))
    for e in todo:
        eq = spec.equalities[e]
        names = closure_site_names(model, e)
        for body_id, name, (pos, quat) in zip((model.eq_obj1id[e], model.eq_obj2id[e]), names, anchors(model, e)):
            body = spec.worldbody if body_id == 0 else \
                spec.body(mujoco.mj_id2name(model, _OBJ.mjOBJ_BODY, int(body_id)))
            body.add_site(name=name, pos=pos, quat=quat)
        eq.objtype = _OBJ.mjOBJ_SITE
        eq.name1, eq.name2 = names
        data = np.zeros_like(eq.data)
        data[6:10] = _IDENTITY                  # a site-based weld: the two site frames coincide
        data[10] = eq.data[10]                  # torquescale
        eq.data = data
    return spec.compile()


def sites_for_body_closures(root: ET.Element, model: mujoco.MjModel) -> None:
    """Rewrite, in an MJCF document ``root`` whose compiled form (with
    :func:`compile_with_site_closures`) is ``model``, every active body-based connect/weld as the
    site-based one ``model`` holds: the two sites added (empty; a writer fills in their frames) and the
    equality pointed at them; closures ``model`` has no such sites for are left as written. For writers of
    calibrated models (:mod:`pmcal.twin.export`)."""
    bodies = {el.get("name"): el for el in root.iter("body") if el.get("name")}
    world = root.find("worldbody")
    e = -1
    for section in root.findall("equality"):
        for el in section:
            e += 1
            if el.tag not in ("connect", "weld") or "body1" not in el.attrib or el.get("active") == "false":
                continue
            names = closure_site_names(model, e)
            if any(mujoco.mj_name2id(model, _OBJ.mjOBJ_SITE, n) < 0 for n in names):
                continue                        # a model compiled as written (not by this module)
            for body_name, site in zip((el.get("body1"), el.get("body2")), names):
                parent = world if body_name in (None, "world") else bodies[body_name]
                parent.append(ET.Element("site", name=site))
            for a in ("body1", "body2", "anchor", "relpose"):
                el.attrib.pop(a, None)
            el.set("site1", names[0])
            el.set("site2", names[1])


def solve_stacked(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A^-1 B`` for a stack of square matrices ``A`` (M, k, k) and right-hand sides ``B`` (M, k) or
    (M, k, m). Rows whose ``A`` is singular (a configuration at the singularity, a pose the solve gave
    up) come back as NaN; numpy's batched solve fails as a whole, so those rows are redone one by one."""
    vec = B.ndim == A.ndim - 1
    Bm = B[..., None] if vec else B
    try:
        out = np.linalg.solve(A, Bm)
    except np.linalg.LinAlgError:
        out = np.full(Bm.shape, np.nan)
        for i in range(len(A)):
            try:
                out[i] = np.linalg.solve(A[i], Bm[i])
            except np.linalg.LinAlgError:
                pass
    return out[..., 0] if vec else out
