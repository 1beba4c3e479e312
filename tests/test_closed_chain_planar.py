"""The generic closed-chain core on the seeded planar robot (mjcf/planar_2dof/chain/machine.toml), checked
against a closed form written here (circle intersections of the planar five-bar, the measuring scale's
distance |O1 O2|), not against pmcal.mechanism.planar: the distance measurement kind, the task frame, the
paper's names mapped onto frame errors, exact derivatives, and identification from scale readings.

Seed geometry (docs/planar.md, Table 1), mm: A1 = (80, 0), A2 = (-80, 0), proximal 375, distal 825,
O1 = (0, -79), O2 = P + (0, 51); angles counter-clockwise from +x; the platform below the base.
"""

from __future__ import annotations

import numpy as np
import pytest

from pmcal.calib.chain_model import NamedModel
from pmcal.calib.closed_chain import crlb, identify_chain, reading_operator
from pmcal.errors import InputError
from pmcal.mechanism.machine_spec import MachineSpec
from pmcal.mjcf import machine_dir

NAMES = ("dtheta1", "dtheta2", "de1x", "de1y", "de2x", "de2y", "dL1", "dL2", "dl1", "dl2", "drMx", "drMy")
ERR = dict(zip(NAMES, (0.5, -0.3, 0.03, -0.02, -0.02, 0.01, 0.01, 0.02, -0.03, -0.02, 1.0, 0.5)))
TASK = np.array([[-240.0, -632.0], [0.0, -632.0], [240.0, -632.0], [-240.0, -782.0], [0.0, -782.0],
                 [240.0, -782.0], [150.0, -900.0], [-400.0, -500.0]])


def _geometry(err: dict | None = None) -> dict:
    e = {k: 0.0 for k in NAMES} | (err or {})
    return dict(A=np.array([[80.0 + e["de1x"], e["de1y"]], [-80.0 + e["de2x"], e["de2y"]]]),
                L=np.array([375.0 + e["dL1"], 375.0 + e["dL2"]]), l=np.array([825.0 + e["dl1"], 825.0 + e["dl2"]]),
                O1=np.array([e["drMx"], -79.0 + e["drMy"]]), zero=np.array([e["dtheta1"], e["dtheta2"]]))


def _circles(c1, r1, c2, r2):
    """The two intersections (n, 2) each of circles (c1, r1) and (c2, r2), c (n, 2)."""
    v = c2 - c1
    d = np.linalg.norm(v, axis=1)
    a = (r1**2 - r2**2 + d**2) / (2 * d)
    h = np.sqrt(r1**2 - a**2)
    mid = c1 + (a / d)[:, None] * v
    perp = np.stack([-v[:, 1], v[:, 0]], axis=1) / d[:, None]
    return mid + h[:, None] * perp, mid - h[:, None] * perp


def closed_forward(cmd_deg: np.ndarray, err: dict | None = None) -> np.ndarray:
    """Platform point P (n, 2) mm for motor commands (n, 2) deg: the distal circles about the elbows, the
    lower intersection (the platform hangs below)."""
    g = _geometry(err)
    th = np.deg2rad(cmd_deg + g["zero"])
    B = g["A"][None] + g["L"][None, :, None] * np.stack([np.cos(th), np.sin(th)], axis=2)
    p, q = _circles(B[:, 0], g["l"][0], B[:, 1], g["l"][1])
    return np.where((p[:, 1] < q[:, 1])[:, None], p, q)


def closed_inverse(task: np.ndarray, err: dict | None = None) -> np.ndarray:
    """Motor commands (n, 2) deg putting P at ``task`` (n, 2) mm: each elbow where the proximal circle about
    A_i meets the distal circle about P, limb 1's elbow outwards (+x), limb 2's outwards (-x)."""
    g = _geometry(err)
    out = []
    for i, pick in ((0, np.argmax), (1, np.argmin)):
        A = np.broadcast_to(g["A"][i], task.shape)
        p, q = _circles(A, g["L"][i], task, g["l"][i])
        B = np.where((pick(np.stack([p[:, 0], q[:, 0]]), axis=0) == 0)[:, None], p, q)
        th = np.rad2deg(np.arctan2(B[:, 1] - A[:, 1], B[:, 0] - A[:, 0]))
        out.append(np.mod(th, 360.0) if i == 1 else th)
    return np.stack(out, axis=1) - g["zero"]


def closed_distance(cmd_deg: np.ndarray, err: dict | None = None) -> np.ndarray:
    """|O1 O2| (n,) mm, O2 = P + (0, 51)."""
    g = _geometry(err)
    return np.linalg.norm(closed_forward(cmd_deg, err) + np.array([0.0, 51.0]) - g["O1"], axis=1)


@pytest.fixture(scope="module")
def planar():
    from pmcal.twin.closed_chain import ClosedChainTwin

    spec = MachineSpec.load(machine_dir("planar_2dof") / "chain")
    twin = ClosedChainTwin(spec)
    return twin, NamedModel(twin, spec.names)


def test_spec_reads_the_distance_measurement():
    spec = MachineSpec.load(machine_dir("planar_2dof") / "chain")
    assert spec.measure == "distance" and spec.reference == "previous" and spec.targets == ("O1", "O2")
    assert spec.task.frame == "O" and set(spec.names) == set(NAMES)
    assert spec.names["de1x"] == ("right_proximal.dx", "right_passive.dx")


def test_forward_inverse_and_distance_match_the_closed_form(planar):
    _, named = planar
    cmd = closed_inverse(TASK)
    np.testing.assert_allclose(named.forward(cmd), TASK, atol=1e-8)
    for err in (None, ERR):
        np.testing.assert_allclose(named.forward(cmd, err), closed_forward(cmd, err), atol=1e-8)
        np.testing.assert_allclose(named.observe(cmd, err)[:, 0], closed_distance(cmd, err), atol=1e-8)
        np.testing.assert_allclose(named.inverse(TASK, err), closed_inverse(TASK, err), atol=1e-7)


def test_distance_derivative_is_exact(planar):
    """The IFT derivative of |O1 O2| against central differences of the closed form (step 1e-4: truncation
    ~1e-8 of a derivative of size ~1)."""
    _, named = planar
    cmd = closed_inverse(TASK)
    J = named.observation_jacobian(cmd, ERR)[:, 0]
    h = 1e-4
    for j, k in enumerate(NAMES):
        up, down = dict(ERR), dict(ERR)
        up[k] += h
        down[k] -= h
        fd = (closed_distance(cmd, up) - closed_distance(cmd, down)) / (2 * h)
        np.testing.assert_allclose(J[:, j], fd, atol=2e-6, err_msg=k)


def test_reading_operator():
    np.testing.assert_array_equal(reading_operator(3), [[-1, 1, 0], [0, -1, 1]])
    np.testing.assert_array_equal(reading_operator(4, "first"), [[-1, 1, 0, 0], [-1, 0, 1, 0], [-1, 0, 0, 1]])
    np.testing.assert_array_equal(reading_operator(4, segments=[1, 1, 2, 2]), [[-1, 1, 0, 0], [0, 0, -1, 1]])


def test_identification_from_scale_readings(planar):
    """The paper's four unknowns from readings of the closed form: exact without noise; with the scale's
    noise the spread over seeds matches the CRLB the core reports."""
    _, named = planar
    keys = ["dtheta1", "dtheta2", "drMx", "drMy"]
    truth = {"dtheta1": 0.5, "dtheta2": -0.25, "drMx": 1.0, "drMy": 0.5}
    cmd = closed_inverse(TASK)
    D = reading_operator(len(cmd))
    readings = D @ closed_distance(cmd, truth)
    res = identify_chain(named, cmd, readings, keys=keys, prior=False)
    assert res.rank == 4
    for k in keys:
        assert res.params[k] == pytest.approx(truth[k], abs=1e-7)
    bound = crlb(named, cmd, truth, keys)
    rng = np.random.default_rng(3)
    sigma = named.sigma_mm
    est = [identify_chain(named, cmd, readings + rng.normal(0, sigma, readings.shape), keys=keys,
                          prior=False).params["dtheta1"] for _ in range(40)]
    spread = np.std(est, ddof=1)
    assert 0.6 * bound[0] < spread < 1.5 * bound[0]        # 40 draws: the std estimate within ~25 %


def _copy(tmp_path, text: str):
    """A machine folder holding ``text`` as its machine.toml, the model given by absolute path."""
    folder = tmp_path / "planar"
    folder.mkdir()
    model = str(machine_dir("planar_2dof") / "planar_2dof.xml")
    (folder / "machine.toml").write_text(text.replace("../planar_2dof.xml", model))
    return folder


TOML = machine_dir("planar_2dof") / "chain" / "machine.toml"


@pytest.mark.parametrize("tracker, message", [
    ('targets = ["O1", "O2", "P"]\nmeasure = "distance"\n', "exactly 2 sites"),
    ('targets = ["O1", "O2"]\nreference = "previous"\n', "only a 'distance' measurement"),
    ('targets = ["O1", "O2"]\nmeasure = "distance"\nreference = "last"\n', "previous, first"),
])
def test_bad_distance_tables_name_the_key(tmp_path, tracker, message):
    text = TOML.read_text()
    start = text.index("[tracker]")
    end = text.index("sigma_mm", start)
    with pytest.raises(InputError, match=message):
        MachineSpec.load(_copy(tmp_path, text[:start] + "[tracker]\n" + tracker + text[end:]))


def test_bad_name_map_names_the_key(tmp_path):
    text = TOML.read_text().replace('dl2 = "left_distal_tip.dx"', 'dl2 = "left_distal_tip.dq"')
    with pytest.raises(InputError, match=r"names\.dl2.*not a frame error"):
        MachineSpec.load(_copy(tmp_path, text))
