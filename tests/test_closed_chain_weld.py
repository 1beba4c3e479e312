"""A loop closed by a site-based weld (position and orientation), on a minimal planar machine written here:
arm A (motor, then a passive hinge) and arm B (two passive hinges) whose end frames are welded together.
The IFT Jacobian (orientation rows included) against central differences, and the closure itself."""

import numpy as np
import pytest

from chain_references import central_differences
from pmcal.twin.closed_chain import ClosedChainTwin

# Home: qa1 = 60, qa2 = -120 deg puts A's end at (0.3, 0) m facing -60 deg; B (links 0.25, 0.2 m) reaches
# the same frame with qb1 = 100, qb2 = -160 deg from its base at (0.24341204, -0.07299686) m. Beyond
# qa1 ~ 61 deg arm B would have to fold through itself: the motor range stops at 58 deg.
XML = """<mujoco model="welded">
  <compiler angle="degree"/>
  <worldbody>
    <body name="a1"><joint name="qa1" axis="0 0 1"/><geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.01"/>
      <body name="a2" pos="0.3 0 0"><joint name="qa2" axis="0 0 1"/>
        <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.01"/>
        <site name="a_end" pos="0.3 0 0"/><site name="nest" pos="0.25 0.05 0.02"/>
      </body>
    </body>
    <body name="b1" pos="0.2434120444 -0.0729968602 0"><joint name="qb1" axis="0 0 1"/>
      <geom type="capsule" fromto="0 0 0 0.25 0 0" size="0.01"/>
      <body name="b2" pos="0.25 0 0"><joint name="qb2" axis="0 0 1"/>
        <geom type="capsule" fromto="0 0 0 0.2 0 0" size="0.01"/><site name="b_end" pos="0.2 0 0"/>
      </body>
    </body>
  </worldbody>
  <equality><weld name="closure" site1="a_end" site2="b_end"/></equality>
  <keyframe><key name="home" qpos="1.0471975512 -2.0943951024 1.7453292520 -2.7925268032"/></keyframe>
</mujoco>
"""
TOML = """[machine]
model = "welded.xml"
[[motors]]
joint = "qa1"
range = [20.0, 58.0]
[tracker]
targets = ["nest"]
sigma_mm = 0.01
[task]
site = "a_end"
coordinates = ["rz_deg"]
[workspace]
rz_deg = [-90.0, -30.0]
[errors]
components = ["dx", "dy", "drz"]    # in the plane: out-of-plane errors make the planar weld inconsistent
"""


@pytest.fixture(scope="module")
def twin(tmp_path_factory):
    d = tmp_path_factory.mktemp("welded")
    (d / "welded.xml").write_text(XML)
    (d / "machine.toml").write_text(TOML)
    return ClosedChainTwin.from_folder(d)


def test_weld_closes_position_and_orientation(twin):
    assert twin.n_equations == 6 and twin.closures[0].weld and len(twin.passive) == 3
    q = twin.solve(np.array([[35.0], [55.0]]), {"b2.dx": 0.3, "a_end.dy": -0.2, "b1.drz": 0.1})
    assert np.isfinite(q).all()
    for row in q:
        twin._kin(row, jac=False)
        d = twin.data
        a, b = twin.points[twin._c1[0]], twin.points[twin._c2[0]]
        np.testing.assert_allclose(d.site_xpos[a], d.site_xpos[b], atol=1e-12)
        np.testing.assert_allclose(d.site_xmat[a], d.site_xmat[b], atol=1e-10)


def test_weld_ift_jacobian_matches_central_differences(twin):
    rng = np.random.default_rng(6)
    keys = twin.error_keys
    assert {"a_end.dx", "b_end.dy", "b1.drz", "m1.dzero"} <= set(keys) and "a1.drx" not in keys
    params = dict(zip(keys, rng.normal(0.0, 0.3, len(keys))))
    cmd = np.array([[30.0], [45.0], [55.0]])
    J = twin.jacobian(cmd, params)
    fd = central_differences(lambda p: twin.targets(cmd, p), params, keys)
    np.testing.assert_allclose(J, fd, atol=1e-6)
    assert np.abs(J).max() > 1.0
