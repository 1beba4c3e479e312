"""Geometric error parameters of the over-constrained PM (docs/formats.md §1, paper Table 1).

Keys at every interface: ``L<j>.<name>`` for limb j = 1..4 and ``SS.<name>``; mm and degrees. Inside
:class:`ErrorSet` the angles are radians. A missing key means zero error (nominal).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

LIMB_FIELDS: tuple[str, ...] = ("dbx", "dby", "dbz", "dalpha", "dgamma", "dl1", "dl2",
                                "dax", "day", "daz", "dmu", "dnu", "dtheta")
SS_FIELDS: tuple[str, ...] = ("dh", "dcx", "dcy", "dcz")
ANGULAR_FIELDS = frozenset({"dalpha", "dgamma", "dmu", "dnu", "dtheta"})

#: The paper's 11 parameters a limb (Table 1/2), in the paper's order.
PAPER_LIMB_FIELDS: tuple[str, ...] = ("dbx", "dby", "dbz", "dalpha", "dgamma", "dl1", "dl2",
                                     "dax", "day", "daz", "dtheta")

DESCRIPTIONS: dict[str, str] = {
    "dbx": "moves B_{j} along base x", "dby": "moves B_{j} along base y", "dbz": "moves B_{j} along base z",
    "dalpha": "tilts limb {j}'s base revolute axis about its radial direction x_{j}",
    "dgamma": "turns limb {j}'s base revolute axis about the vertical z_{j}",
    "dl1": "lengthens link B_{j}-S_{j}", "dl2": "lengthens link S_{j}-A_{j}",
    "dax": "moves A_{j} along platform u", "day": "moves A_{j} along platform v",
    "daz": "moves A_{j} along platform w",
    "dmu": "tilts limb {j}'s platform revolute axis about its radial direction",
    "dnu": "turns limb {j}'s platform revolute axis about the platform normal",
    "dtheta": "offsets motor {j}'s zero",
    "dh": "lengthens the SS limb", "dcx": "moves the SS platform joint centre along u",
    "dcy": "moves the SS platform joint centre along v", "dcz": "moves the SS platform joint centre along w",
}

#: Paper 000 Table 2, "Predefined" column (mm, deg), mapped by name onto pmcal's keys (docs/formats.md). Decision
#: (docs/ocpm_2dof.md): the values keep pmcal's frames (B in base axes, A in platform axes) for both
#: limbs; the paper's appendix expresses limb 2 in a frame turned by 90 deg, pmcal does not.
PAPER_TABLE2: dict[str, float] = {
    "L1.dbx": -1.5, "L1.dby": 1.3, "L1.dbz": -1.0, "L1.dalpha": 0.0, "L1.dgamma": -0.1,
    "L1.dl1": 0.382, "L1.dl2": 1.214, "L1.dax": 1.4, "L1.day": 1.3, "L1.daz": 1.2, "L1.dtheta": -0.28,
    "L2.dbx": -1.0, "L2.dby": -0.45, "L2.dbz": -1.5, "L2.dalpha": 0.2, "L2.dgamma": 0.2,
    "L2.dl1": -0.4, "L2.dl2": 0.5, "L2.dax": 1.5, "L2.day": 2.0, "L2.daz": 0.3, "L2.dtheta": -0.4,
}

#: Paper Table 2, "Identified" column (for the report's side-by-side comparison).
PAPER_TABLE2_IDENTIFIED: dict[str, float] = {
    "L1.dbx": -1.488, "L1.dby": 1.275, "L1.dbz": -1.096, "L1.dalpha": 0.0, "L1.dgamma": -0.11,
    "L1.dl1": 0.213, "L1.dl2": 1.107, "L1.dax": 1.349, "L1.day": 0.901, "L1.daz": 1.119, "L1.dtheta": -0.305,
    "L2.dbx": -1.16, "L2.dby": -0.416, "L2.dbz": -1.489, "L2.dalpha": 0.23, "L2.dgamma": 0.17,
    "L2.dl1": -0.377, "L2.dl2": 0.488, "L2.dax": 1.449, "L2.day": 1.986, "L2.daz": 0.27, "L2.dtheta": -0.37,
}

_KEY = re.compile(r"^(?:L([1-9])\.(\w+)|SS\.(\w+))$")


def is_angular(key: str) -> bool:
    """True for keys given in degrees at the interface (radians inside)."""
    return key.split(".", 1)[-1] in ANGULAR_FIELDS


def unit(key: str) -> str:
    return "deg" if is_angular(key) else "mm"


def describe(key: str) -> str:
    """Plain words for a key, e.g. ``L1.day`` -> ``moves A_1 along platform v``."""
    m = _KEY.match(key)
    if not m:
        return key
    name = m.group(2) or m.group(3)
    return DESCRIPTIONS.get(name, name).format(j=m.group(1) or "")


def all_keys(n_limbs: int = 4, actuated: tuple[int, ...] = (1, 2)) -> list[str]:
    """Every valid key: 12 geometric keys a limb, ``dtheta`` on actuated limbs, and the SS keys."""
    keys = [f"L{j}.{f}" for j in range(1, n_limbs + 1) for f in LIMB_FIELDS
            if f != "dtheta" or j in actuated]
    return keys + [f"SS.{f}" for f in SS_FIELDS]


def check_key(key: str, n_limbs: int = 4, actuated: tuple[int, ...] = (1, 2)) -> str | None:
    """Return an error text for an invalid key, None if valid."""
    m = _KEY.match(key)
    if not m:
        return f"unknown parameter key '{key}' (expected L<j>.<name> or SS.<name>)"
    if m.group(3) is not None:
        return None if m.group(3) in SS_FIELDS else f"unknown SS parameter '{key}' (known: {', '.join(SS_FIELDS)})"
    j, name = int(m.group(1)), m.group(2)
    if not 1 <= j <= n_limbs:
        return f"unknown limb in '{key}' (limbs 1..{n_limbs})"
    if name not in LIMB_FIELDS:
        return f"unknown limb parameter '{key}' (known: {', '.join(LIMB_FIELDS)})"
    if name == "dtheta" and j not in actuated:
        return f"'{key}': limb {j} has no motor (zero offsets exist on limbs {actuated})"
    return None


@dataclass
class ErrorSet:
    """All geometric errors as arrays; mm and radians. Limb index 0..3 is limb 1..4.

    Leading batch dimensions are allowed (shape ``batch + (4, 3)`` etc.), so a whole population of
    candidate parameter sets can be evaluated in one call.
    """

    db: np.ndarray = field(default_factory=lambda: np.zeros((4, 3)))      # B_j offset, base axes
    dalpha: np.ndarray = field(default_factory=lambda: np.zeros(4))
    dgamma: np.ndarray = field(default_factory=lambda: np.zeros(4))
    dl1: np.ndarray = field(default_factory=lambda: np.zeros(4))
    dl2: np.ndarray = field(default_factory=lambda: np.zeros(4))
    da: np.ndarray = field(default_factory=lambda: np.zeros((4, 3)))      # A_j offset, platform axes
    dmu: np.ndarray = field(default_factory=lambda: np.zeros(4))
    dnu: np.ndarray = field(default_factory=lambda: np.zeros(4))
    dtheta: np.ndarray = field(default_factory=lambda: np.zeros(4))       # motor zero offsets
    ss_dh: np.ndarray | float = 0.0
    ss_dc: np.ndarray = field(default_factory=lambda: np.zeros(3))        # SS joint centre, platform axes

    _VEC = {"dbx": ("db", 0), "dby": ("db", 1), "dbz": ("db", 2), "dax": ("da", 0), "day": ("da", 1),
            "daz": ("da", 2)}

    @classmethod
    def from_dict(cls, params: dict[str, float], n_limbs: int = 4,
                  actuated: tuple[int, ...] = (1, 2)) -> "ErrorSet":
        """Build from interface keys (mm, degrees). Raises ``ValueError`` naming a bad key or value."""
        e = cls()
        for key, value in params.items():
            msg = check_key(key, n_limbs, actuated)
            if msg:
                raise ValueError(msg)
            try:
                v = float(value)
            except (TypeError, ValueError):
                raise ValueError(f"'{key}': value {value!r} is not a number") from None
            if not np.isfinite(v):
                raise ValueError(f"'{key}': value {value!r} is not finite")
            e.set(key, np.deg2rad(v) if is_angular(key) else v)
        return e

    def set(self, key: str, value: float) -> None:
        """Set one parameter in internal units (mm, rad)."""
        group, name = key.split(".", 1)
        if group == "SS":
            if name == "dh":
                self.ss_dh = value
            else:
                self.ss_dc[..., "xyz".index(name[-1])] = value
            return
        j = int(group[1:]) - 1
        if name in self._VEC:
            arr, k = self._VEC[name]
            getattr(self, arr)[..., j, k] = value
        else:
            getattr(self, name)[..., j] = value

    def get(self, key: str) -> float:
        """One parameter in internal units (mm, rad)."""
        group, name = key.split(".", 1)
        if group == "SS":
            return float(self.ss_dh) if name == "dh" else float(self.ss_dc["xyz".index(name[-1])])
        j = int(group[1:]) - 1
        if name in self._VEC:
            arr, k = self._VEC[name]
            return float(getattr(self, arr)[j, k])
        return float(getattr(self, name)[j])

    def to_dict(self, keys: list[str] | None = None, nonzero: bool = True) -> dict[str, float]:
        """Interface keys (mm, degrees); by default only the non-zero ones."""
        out = {}
        for key in keys or all_keys():
            v = self.get(key)
            v = float(np.rad2deg(v)) if is_angular(key) else v
            if v != 0.0 or not nonzero:
                out[key] = v
        return out

    def copy(self) -> "ErrorSet":
        return ErrorSet(**{k: np.array(getattr(self, k), dtype=float, copy=True)
                           for k in self.__dataclass_fields__})


def random_errors(rng: np.random.Generator, pos_mm: float = 0.5, ang_deg: float = 0.1,
                  limbs: tuple[int, ...] = (1, 2, 3, 4), ss: bool = True,
                  zero_offsets: bool = True, distribution: str = "uniform") -> dict[str, float]:
    """A random error draw: positions/lengths of size ``pos_mm`` and angles of size ``ang_deg``.

    ``distribution="uniform"`` draws from ±size; ``"normal"`` uses size as standard deviation.
    Returns interface keys (mm, degrees).
    """
    draw = (lambda s: rng.uniform(-s, s)) if distribution == "uniform" else (lambda s: rng.normal(0, s))
    out: dict[str, float] = {}
    for j in limbs:
        for f in LIMB_FIELDS:
            if f == "dtheta" and (j not in (1, 2) or not zero_offsets):
                continue
            out[f"L{j}.{f}"] = float(draw(ang_deg if f in ANGULAR_FIELDS else pos_mm))
    if ss:
        for f in SS_FIELDS:
            out[f"SS.{f}"] = float(draw(pos_mm))
    return out


#: Key of the log closure-stiffness ratio in a whole-chain parameter vector.
LOG_RATIO = "log_stiffness_ratio"


def errors_and_ratio(keys: list[str], x: np.ndarray) -> tuple[ErrorSet, float | None]:
    """ErrorSet (internal units) and log stiffness ratio (or None) from a parameter vector."""
    e = ErrorSet()
    log_ratio = None
    for k, v in zip(keys, x):
        if k == LOG_RATIO:
            log_ratio = float(v)
        else:
            e.set(k, float(v))
    return e, log_ratio


def to_interface(keys: list[str], x: np.ndarray) -> dict[str, float]:
    """Parameter dict in interface units (mm, deg); the stiffness ratio is left out."""
    return {k: float(np.rad2deg(v)) if is_angular(k) else float(v) for k, v in zip(keys, x) if k != LOG_RATIO}
