"""Loop closures written either way (site-based or MuJoCo's body-based connect/weld) give the same
machine: :mod:`pmcal.twin.closures` against MuJoCo's own constraint residuals, and a five-bar written from
scratch (tests/data/fivebar) against its closed form (tests/chain_references.py), through the whole
folder-machine path and the calibrated model's export."""

import json
import shutil

import mujoco
import numpy as np
import pytest

from pmcal.cli import main
from pmcal.errors import InputError
from pmcal.machines import Machine
from pmcal.twin.closures import compile_with_site_closures
from tests.chain_references import fivebar_fk

FIVEBAR = "tests/data/fivebar"
BODY_CONNECT = '<connect name="tip" body1="left_link" body2="right_link" anchor="0.1 0.2 0"/>'

MIXED = """<mujoco><worldbody>
<body name="a"><joint name="ja" type="hinge" axis="0 0 1"/><geom size=".01"/>
 <body name="b" pos="0.1 0 0"><joint name="jb" type="hinge" axis="0 1 0"/><geom size=".01"/></body></body>
<body name="c" pos="0.2 0.05 0.01" euler="10 20 30"><joint name="jc" type="ball"/><geom size=".01"/></body>
<body name="d" pos="-0.2 0.05 0.01"><joint name="jd" type="slide" axis="1 0 0"/>
 <joint name="jd2" type="hinge" axis="0 1 0"/><geom size=".01"/></body>
</worldbody><equality>
<weld name="w" body1="b" body2="c" anchor="0.01 0.02 0.03" relpose="0.1 0.04 0.01 0.9 0.1 0.2 0.3"/>
<weld body1="a" body2="d" anchor="0.01 0 0.03"/>
<connect name="k" body1="b" body2="d" anchor="0.02 0.01 0"/>
<connect name="kw" body1="c" anchor="0.02 0.01 0"/>
</equality></mujoco>"""


def test_converted_closures_have_mujocos_own_residuals(tmp_path):
    """Welds (explicit relpose, and derived from qpos0), connects (one to the world): at 20 random
    configurations the site-based model's equality residuals equal the body-based model's as MuJoCo computes
    them (efc_pos), to rounding."""
    path = tmp_path / "mixed.xml"
    path.write_text(MIXED)
    m0 = mujoco.MjModel.from_xml_path(str(path))
    m1 = compile_with_site_closures(path)
    assert {int(v) for v in m1.eq_objtype} == {int(mujoco.mjtObj.mjOBJ_SITE)}
    names = {mujoco.mj_id2name(m1, mujoco.mjtObj.mjOBJ_SITE, i) for i in range(m1.nsite)}
    assert {"w_site1", "w_site2", "closure1_site1", "k_site2", "kw_site2"} <= names
    rng = np.random.default_rng(0)
    d0, d1 = mujoco.MjData(m0), mujoco.MjData(m1)
    ball = m0.jnt_qposadr[2]
    for _ in range(20):
        q = m0.qpos0 + rng.normal(0.0, 0.3, m0.nq)
        q[ball:ball + 4] /= np.linalg.norm(q[ball:ball + 4])
        res = []
        for m, d in ((m0, d0), (m1, d1)):
            d.qpos[:] = q
            mujoco.mj_forward(m, d)
            res.append(d.efc_pos[d.efc_type == mujoco.mjtConstraint.mjCNSTR_EQUALITY].copy())
        assert len(res[0]) == 18 and np.abs(res[0]).max() > 1e-2
        assert np.abs(res[0] - res[1]).max() < 1e-12


def fivebar_folder(tmp_path, body_based: bool):
    folder = tmp_path / ("fivebar_body" if body_based else "fivebar")
    shutil.copytree(FIVEBAR, folder)
    if body_based:
        xml = folder / "fivebar.xml"
        text = xml.read_text()
        site = '<connect name="tip" site1="left_tip" site2="right_tip"/>'
        assert site in text
        xml.write_text(text.replace(site, BODY_CONNECT))
    return folder


def test_fivebar_matches_its_closed_form_either_way(tmp_path):
    """The nominal five-bar, closed site-based or body-based: tool and SMR where the circle intersection
    puts them (1e-8 mm, the assembly tolerance) over the motor ranges, and with the same errors (the anchor sites named per form)
    the same nests."""
    twins = [Machine.from_folder(fivebar_folder(tmp_path, b)).twin for b in (False, True)]
    cmd = np.random.default_rng(3).uniform(-30.0, 30.0, size=(40, 2))
    tool, smr = fivebar_fk(cmd)
    for twin in twins:
        y = twin.targets(cmd)
        assert np.isfinite(y).all()
        assert np.abs(y[:, 0, :2] - tool).max() < 1e-8 and np.abs(y[:, 1, :2] - smr).max() < 1e-8
        assert np.abs(y[:, 0, 2] - 20.0).max() < 1e-9
    site, body = twins
    assert {"tip_site1.dx", "tip_site2.dy"} <= set(body.error_keys)
    rename = {"left_tip": "tip_site1", "right_tip": "tip_site2"}
    errors = {"left_crank.dx": 0.3, "right_link.drz": 0.05, "left_tip.dy": -0.2, "right_tip.dx": 0.15,
              "m2.dzero": 0.04}
    as_body = {rename.get(k.split(".")[0], k.split(".")[0]) + "." + k.split(".")[1]: v for k, v in errors.items()}
    assert np.abs(site.targets(cmd, errors) - body.targets(cmd, as_body)).max() < 1e-9


def test_body_based_fivebar_whole_chain_and_export(tmp_path, capsys):
    """The body-based five-bar through the command line (measure, identify, targets, compensate, export):
    identification leaves the tracker noise (chi2/dof ~ 1), and the exported model (its closure turned
    site-based) closes the loop at the calibrated assembly, read by plain MuJoCo."""
    folder = fivebar_folder(tmp_path, True)
    argv = ["--quiet", "--machine", str(folder)]
    d = tmp_path
    for cmd in (["twin", "measure", "--poses", "40", "--seed", "2", "-o", d / "m.csv"],
                ["identify", d / "m.csv", "-o", d / "p.json"], ["targets", "-o", d / "tg.csv"],
                ["compensate", d / "p.json", "--targets", d / "tg.csv", "-o", d / "s.csv"],
                ["export-model", d / "p.json", "-o", d / "cal" / "fivebar.xml"]):
        (d / "cal").mkdir(exist_ok=True)
        assert main(argv + [str(c) for c in cmd]) == 0, cmd
    doc = json.loads((d / "p.json").read_text())
    assert 0.6 < doc["chi2_per_dof"] < 1.5          # 160 coordinates, ~16 base errors: chi2/dof 1 +- 0.12
    text = (d / "cal" / "fivebar.xml").read_text()
    assert 'site1="tip_site1"' in text and "body1=" not in text
    mach = Machine.from_folder(folder)
    params = doc["params"]
    cmd = mach.twin.sample_commands(8, np.random.default_rng(4))
    q = mach.twin.solve(cmd, params)
    m = mujoco.MjModel.from_xml_path(str(d / "cal" / "fivebar.xml"))
    data = mujoco.MjData(m)
    shift = mach.twin.errors.zero_offset * mach.twin.motor_unit
    kin = mach.twin.kinematics(q)                    # the twin's closure sites come first among its points
    for qi, xs in zip(q, kin.site_xpos):
        data.qpos[:] = qi
        data.qpos[mach.twin.motor_qadr] -= shift
        mujoco.mj_forward(m, data)
        gap = data.efc_pos[data.efc_type == mujoco.mjtConstraint.mjCNSTR_EQUALITY]
        # a planar loop closed by a connect, with out-of-plane errors: closed in the least-squares sense;
        # MuJoCo reads back the calibrated twin's own compromise (its gap, site1 - site2, m)
        assert np.abs(gap - (xs[0] - xs[1])).max() < 1e-9


_STRETCHED = """<mujoco model="stretched">
  <worldbody>
    <body name="slider" pos="60 0 0">
      <joint name="m1" type="slide" axis="1 0 0"/>
      <geom type="box" size="0.1 0.1 0.1"/>
      <site name="anchor"/>
      <site name="tool" pos="0 0 0.1"/>
    </body>
    <body name="link1">
      <joint name="j1" type="hinge" axis="0 0 1"/>
      <geom type="capsule" fromto="0 0 0 30 0 0" size="0.05"/>
      <body name="link2" pos="30 0 0">
        <joint name="j2" type="hinge" axis="0 0 1"/>
        <geom type="capsule" fromto="0 0 0 30 0 0" size="0.05"/>
        <site name="tip" pos="30 0 0"/>
        <site name="nest1" pos="29.999 0 0"/>
        <site name="nest2" pos="30 0.001 0"/>
      </body>
    </body>
  </worldbody>
  <equality><connect site1="tip" site2="anchor"/></equality>
  <keyframe><key name="home" qpos="HOME"/></keyframe>
</mujoco>
"""


def _slider_loop(folder, xml):
    """Write the model ``xml`` (a loop closed on the slider ``m1``, nests ``nest1``, ``nest2``, the task site
    ``tool``; lengths in m) and its machine.toml (mm) into ``folder``."""
    (folder / "sing.xml").write_text(xml)
    (folder / "machine.toml").write_text(
        '[machine]\nname = "sing"\nmodel = "sing.xml"\n\n[[motors]]\njoint = "m1"\nrange = [-9000.0, 0.0]\n\n'
        '[tracker]\ntargets = ["nest1", "nest2"]\nsigma_mm = 0.01\n\n[task]\nsite = "tool"\ncoordinates = ["x_mm"]\n\n'
        '[workspace]\nx_mm = [51000.0, 59000.0]\n\n[errors]\nframes = "all"\n')


def _refusal(folder, xml, refused, n_free):
    """The message of the InputError (on ``[[motors]]``) that loading the slider loop ``xml`` in ``folder``
    raises if ``refused``, else "" after checking the machine loads with ``n_free`` free directions."""
    _slider_loop(folder, xml)
    if not refused:
        assert Machine.from_folder(folder).twin.n_free == n_free
        return ""
    with pytest.raises(InputError) as exc:
        Machine.from_folder(folder).twin
    assert exc.value.field == "motors", str(exc.value)
    return str(exc.value)


@pytest.mark.parametrize("offset, near", [(0.0003, True), (0.0, False)])
def test_an_axis_nearly_through_another_joint_is_named(tmp_path, offset, near):
    """The same two links bent (elbow 0.5 rad), the second carrying a third hinge parallel to the elbow whose
    axis passes ``offset`` (m) from the elbow's. Gepetto's Disney-like leg has a hinge 0.295 mm from a ball's
    centre: the pair nearly repeats a rotation, so a free direction turns the nests (0.06 mm/rad here) at every
    home, and the refusal told the user to store a home away from a singular pose, which no home satisfies.
    It now names the two joints and the offset. On the axis (offset 0) the hinge repeats the elbow exactly:
    the free direction moves nothing and the machine loads."""
    home = f"{60 * (float(np.cos(0.5)) - 1)!r} 0.5 -1.0 0"
    end = (f'<body name="end" pos="0 {offset} 0"><joint name="j3" type="hinge" axis="0 0 1"/>'
           f'<geom type="capsule" fromto="0 {-offset} 0 30 {-offset} 0" size="0.05"/>'
           f'<site name="tip" pos="30 {-offset} 0"/><site name="nest1" pos="15 {-offset} 0"/>'
           f'<site name="nest2" pos="15 0.001 0"/></body>')
    xml = _STRETCHED.replace("HOME", home).replace(
        '<geom type="capsule" fromto="0 0 0 30 0 0" size="0.05"/>\n        <site name="tip" pos="30 0 0"/>\n'
        '        <site name="nest1" pos="29.999 0 0"/>\n        <site name="nest2" pos="30 0.001 0"/>',
        '<geom type="sphere" size="0.1"/>' + end)
    assert "j3" in xml
    msg = _refusal(tmp_path, xml, refused=near, n_free=1)
    if not near:
        return
    assert "j2" in msg and "j3" in msg, msg
    assert "axis passes 0.3 mm from joint" in msg and "no home helps" in msg and "singular pose" not in msg, msg


@pytest.mark.parametrize("home, refused", [("0 0 0", True), (f"{60 * (float(np.cos(0.5)) - 1)!r} 0.5 -1.0", False)])
def test_a_home_at_a_singular_pose_is_refused(tmp_path, home, refused):
    """Two 30 m links closed on a slider, the nests 1 mm from where they meet it. Stretched straight (home
    0 0 0) the loop is singular: the elbow is free to first order and turns the nests, by 0.45 mm per rad
    of that free direction. Gepetto's Disney-like leg, with such a free direction at home (from a drawing's
    near-repeated rotation, test_an_axis_nearly_through_another_joint_is_named), loaded
    (0.2-0.6 mm/rad was below 1 % of its size per rad, the allowance for export-model outputs), and its
    solves then landed 0.06 mm apart depending on where they started: its own twin's data fitted at chi2/dof
    1.9. A model as drawn is refused, naming the joints, the motion and the singular pose; bent (elbow
    0.5 rad), the same machine loads."""
    msg = _refusal(tmp_path, _STRETCHED.replace("HOME", home), refused=refused, n_free=0)
    if not refused:
        return
    assert "singular pose" in msg and "j1" in msg and "j2" in msg, msg
    assert 0.40 < float(msg.split(" mm/rad at home")[0].rsplit("; ", 1)[1]) < 0.50, msg
