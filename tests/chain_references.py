"""Closed-form references for the data-only machines, written from the textbook geometry, not from pmcal.

Delta (Clavel): per arm, the elbow E_i = B_i + La (cos t u_i - sin t z) must lie at distance Lf from the
platform point P_i = p + Rp u_i (the parallelogram keeps the platform parallel to the base, so the
midpoints of its rod pairs stay Lf apart): inverse kinematics is a circle-sphere intersection per arm
(``A cos t + B sin t = C``), forward kinematics the intersection of three spheres (trilateration).

Gough-Stewart hexapod: leg lengths l_i = |p + R b_i - a_i| (inverse); the forward kinematics by a Newton
iteration on the six leg-length equations with a numerical Jacobian (written here, independent of the
twin's solver).

Dimensions are those published in mjcf/<machine>/README.md, typed here again.
"""

from __future__ import annotations

import numpy as np

# ----------------------------------------------------------------------------------------------- Delta
DELTA = dict(Rb=200.0, La=350.0, Lf=800.0, Rp=60.0, tcp=-40.0, phi=(0.0, 120.0, 240.0),
             nests=((50.0, 0.0, -20.0), (-25.0, 43.30127019, -20.0), (-25.0, -43.30127019, -20.0)))


def _rz(deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    return np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])


def delta_ik(p: np.ndarray, d: dict = DELTA) -> np.ndarray:
    """Motor angles (N, 3) deg (0 = arm horizontal, positive down) for platform centres p (N, 3) mm."""
    p = np.atleast_2d(p)
    out = np.empty((len(p), 3))
    for i, phi in enumerate(d["phi"]):
        q = p @ _rz(phi)                              # platform centre in the arm's frame (R^T p)
        x, y, z = q[:, 0] + d["Rp"] - d["Rb"], q[:, 1], q[:, 2]
        A, B = 2 * d["La"] * x, -2 * d["La"] * z
        C = d["La"] ** 2 + x * x + y * y + z * z - d["Lf"] ** 2
        out[:, i] = np.rad2deg(np.arctan2(B, A) - np.arccos(C / np.hypot(A, B)))
    return out


def delta_fk(theta_deg: np.ndarray, d: dict = DELTA) -> np.ndarray:
    """Platform centres (N, 3) mm for motor angles (N, 3) deg: the lower intersection of three spheres."""
    th = np.deg2rad(np.atleast_2d(theta_deg))
    out = np.empty((len(th), 3))
    for n in range(len(th)):
        c = []
        for i, phi in enumerate(d["phi"]):
            e = np.array([d["Rb"] + d["La"] * np.cos(th[n, i]) - d["Rp"], 0.0, -d["La"] * np.sin(th[n, i])])
            c.append(_rz(phi) @ e)
        p1, p2, p3 = c
        ex = (p2 - p1) / np.linalg.norm(p2 - p1)
        i_ = ex @ (p3 - p1)
        ey = p3 - p1 - i_ * ex
        ey /= np.linalg.norm(ey)
        ez = np.cross(ex, ey)
        dd = np.linalg.norm(p2 - p1)
        j = ey @ (p3 - p1)
        r = d["Lf"]
        x = dd / 2.0                                   # equal radii
        y = (i_ * i_ + j * j - 2 * i_ * x) / (2 * j)
        z = np.sqrt(r * r - x * x - y * y)
        a, b = p1 + x * ex + y * ey + z * ez, p1 + x * ex + y * ey - z * ez
        out[n] = a if a[2] < b[2] else b
    return out


# ---------------------------------------------------------------------------------------------- hexapod
HEXAPOD = dict(Ra=250.0, Rb=150.0, height=400.0,
               base_deg=(-15.0, 15.0, 105.0, 135.0, 225.0, 255.0),
               platform_deg=(-45.0, 45.0, 75.0, 165.0, 195.0, 285.0))


def hexapod_points(d: dict = HEXAPOD) -> tuple[np.ndarray, np.ndarray]:
    """Base joint centres a_i (6, 3) (base frame) and platform joint centres b_i (6, 3) (platform frame), mm."""
    a = np.array([[d["Ra"] * np.cos(np.deg2rad(t)), d["Ra"] * np.sin(np.deg2rad(t)), 0.0] for t in d["base_deg"]])
    b = np.array([[d["Rb"] * np.cos(np.deg2rad(t)), d["Rb"] * np.sin(np.deg2rad(t)), 0.0]
                  for t in d["platform_deg"]])
    return a, b


def rpy_matrix(rx: float, ry: float, rz: float) -> np.ndarray:
    """R = Rz(rz) Ry(ry) Rx(rx), angles deg."""
    x, y, z = np.deg2rad([rx, ry, rz])
    Rx = np.array([[1, 0, 0], [0, np.cos(x), -np.sin(x)], [0, np.sin(x), np.cos(x)]])
    Ry = np.array([[np.cos(y), 0, np.sin(y)], [0, 1, 0], [-np.sin(y), 0, np.cos(y)]])
    Rz = np.array([[np.cos(z), -np.sin(z), 0], [np.sin(z), np.cos(z), 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def hexapod_ik(pose: np.ndarray, d: dict = HEXAPOD) -> np.ndarray:
    """Leg lengths (N, 6) mm for platform poses (N, 6) = (x, y, z mm, rx, ry, rz deg)."""
    a, b = hexapod_points(d)
    pose = np.atleast_2d(pose)
    out = np.empty((len(pose), 6))
    for n, (x, y, z, rx, ry, rz) in enumerate(pose):
        R = rpy_matrix(rx, ry, rz)
        out[n] = np.linalg.norm(np.array([x, y, z]) + b @ R.T - a, axis=1)
    return out


def hexapod_fk(lengths: np.ndarray, d: dict = HEXAPOD, start=None, tol: float = 1e-12) -> np.ndarray:
    """Platform poses (N, 6) for leg lengths (N, 6) mm: Newton on l(pose) - lengths, numerical Jacobian,
    from the home pose (0, 0, height, 0, 0, 0)."""
    lengths = np.atleast_2d(lengths)
    out = np.empty((len(lengths), 6))
    for n, target in enumerate(lengths):
        x = np.array([0.0, 0.0, d["height"], 0.0, 0.0, 0.0]) if start is None else np.array(start, float)
        for _ in range(50):
            r = hexapod_ik(x, d)[0] - target
            if np.max(np.abs(r)) < tol:
                break
            J = np.empty((6, 6))
            for k in range(6):
                h = np.zeros(6)
                h[k] = 1e-6
                J[:, k] = (hexapod_ik(x + h, d)[0] - hexapod_ik(x - h, d)[0]) / 2e-6
            x = x - np.linalg.solve(J, r)
        out[n] = x
    return out


# ------------------------------------------------------------------------------- finite differences
def central_differences(fn, params: dict, keys: list[str], h: float | dict = 1e-4) -> np.ndarray:
    """d fn(params) / d params[k] for every k in ``keys`` by central differences (step ``h`` in the keys'
    units, or ``h[k]`` per key): ``fn`` maps a parameter dict to an array; the result has a last axis over
    ``keys``."""
    cols = []
    for k in keys:
        step = h[k] if isinstance(h, dict) else h
        up, dn = dict(params), dict(params)
        up[k] = up.get(k, 0.0) + step
        dn[k] = dn.get(k, 0.0) - step
        cols.append((fn(up) - fn(dn)) / (2 * step))
    return np.stack(cols, axis=-1)


#: the five-bar of tests/data/fivebar (mm): crank hinges at x = -+100, cranks 200 along +y at motor 0,
#: links from the crank tips to the tool, 223.6 mm (100, 200 at home)
FIVEBAR = {"base": 100.0, "crank": 200.0, "link": float(np.hypot(100.0, 200.0))}


def fivebar_fk(theta_deg: np.ndarray, d: dict = FIVEBAR) -> tuple[np.ndarray, np.ndarray]:
    """Tool point and the left link's midpoint (N, 2) mm of the five-bar at motor angles (N, 2) deg
    (left, right; positive turns the crank counter-clockwise about +z): the crank tips, then the upper
    intersection of the two circles of link length around them."""
    t = np.deg2rad(np.atleast_2d(theta_deg))
    a = np.stack([-d["base"] - d["crank"] * np.sin(t[:, 0]), d["crank"] * np.cos(t[:, 0])], axis=1)
    b = np.stack([d["base"] - d["crank"] * np.sin(t[:, 1]), d["crank"] * np.cos(t[:, 1])], axis=1)
    mid, half = (a + b) / 2.0, np.linalg.norm(b - a, axis=1) / 2.0
    h = np.sqrt(d["link"] ** 2 - half ** 2)
    u = (b - a) / (2.0 * half[:, None])
    normal = np.stack([-u[:, 1], u[:, 0]], axis=1)          # left of a -> b: +y at home
    tool = mid + h[:, None] * normal
    return tool, (a + tool) / 2.0
