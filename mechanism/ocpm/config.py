"""Nominal geometry of the over-constrained PM, loaded from ``mjcf/ocpm_2dof/machine.toml``.

Frames (docs/formats.md §1): base frame O-xyz at the SS limb's base sphere centre, z up; platform frame
C_E-uvw defined by the tracker targets. Limb j sits at azimuth psi_j. Units: mm, radians, kg.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np
from pmcal.mjcf import machine_dir

MACHINE_DIR = machine_dir("ocpm_2dof")


class ConfigError(ValueError):
    """A machine configuration file is invalid (names the file and the key)."""


@dataclass(frozen=True)
class Geometry:
    """Nominal geometry (mm, rad) plus the twin's defaults."""

    a: float = 150.0
    h: float = 402.0
    l: float = 317.0
    hs: float = 80.0
    psi: np.ndarray = field(default_factory=lambda: np.deg2rad([0.0, 90.0, 180.0, 270.0]))
    actuated: tuple[int, ...] = (1, 2)
    targets: np.ndarray = field(default_factory=lambda: np.array(
        [[100.0, 0.0, 80.0], [-50.0, 86.6025, 80.0], [-50.0, -86.6025, 80.0]]))
    target_names: tuple[str, ...] = ("T1", "T2", "T3")
    platform_mass: float = 6.0
    platform_com: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 40.0]))
    link_mass: float = 0.5
    ss_mass: float = 0.5
    passive_closure_stiffness: float = 1.0e3   # N/mm
    stiffness_ratio: float = 1000.0
    theta_max: float = np.deg2rad(60.0)
    motor_min: float = np.deg2rad(-150.0)
    motor_max: float = np.deg2rad(60.0)
    sigma_mm: float = 0.01

    @property
    def n_limbs(self) -> int:
        return int(self.psi.size)

    def base_points(self) -> np.ndarray:
        """Nominal B_j in the base frame, (4, 3) mm."""
        return np.stack([self.a * np.cos(self.psi), self.a * np.sin(self.psi), np.zeros_like(self.psi)], 1)

    def platform_points(self) -> np.ndarray:
        """Nominal A_j in platform coordinates, (4, 3) mm."""
        return self.base_points()


def _vec(doc: dict, key: str, n: int, path: Path, section: str) -> np.ndarray:
    try:
        v = np.asarray(doc[key], dtype=float)
    except KeyError:
        raise ConfigError(f"{path}: [{section}] missing key '{key}'") from None
    except (TypeError, ValueError):
        raise ConfigError(f"{path}: [{section}] key '{key}' must be a list of numbers") from None
    if v.shape != (n,) or not np.all(np.isfinite(v)):
        raise ConfigError(f"{path}: [{section}] key '{key}' must be {n} finite numbers")
    return v


def _pos(doc: dict, key: str, path: Path, section: str) -> float:
    try:
        v = float(doc[key])
    except KeyError:
        raise ConfigError(f"{path}: [{section}] missing key '{key}'") from None
    except (TypeError, ValueError):
        raise ConfigError(f"{path}: [{section}] key '{key}' must be a number") from None
    if not np.isfinite(v) or v <= 0:
        raise ConfigError(f"{path}: [{section}] key '{key}' must be positive, got {v}")
    return v


def load_geometry(path: str | Path | None = None) -> Geometry:
    """Read and validate a machine.toml (default: the built-in machine)."""
    path = Path(path) if path is not None else MACHINE_DIR / "machine.toml"
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read machine configuration: {exc}") from None
    g, t = doc.get("geometry", {}), doc.get("targets", {})
    inert, comp = doc.get("inertia", {}), doc.get("compliance", {})
    ws, tr = doc.get("workspace", {}), doc.get("tracker", {})
    names = tuple(sorted(t, key=lambda k: (len(k), k)))
    if len(names) < 3:
        raise ConfigError(f"{path}: [targets] needs at least 3 tracker targets")
    targets = np.stack([_vec(t, k, 3, path, "targets") for k in names])
    psi = _vec(g, "limb_angles_deg", 4, path, "geometry")
    return Geometry(
        a=_pos(g, "a", path, "geometry"), h=_pos(g, "h", path, "geometry"),
        l=_pos(g, "l", path, "geometry"), hs=_pos(g, "hs", path, "geometry"),
        psi=np.deg2rad(psi), actuated=tuple(int(j) for j in g.get("actuated_limbs", (1, 2))),
        targets=targets, target_names=names,
        platform_mass=_pos(inert, "platform_mass", path, "inertia"),
        platform_com=_vec(inert, "platform_com", 3, path, "inertia"),
        link_mass=_pos(inert, "link_mass", path, "inertia"),
        ss_mass=_pos(inert, "ss_mass", path, "inertia"),
        passive_closure_stiffness=_pos(comp, "passive_closure_stiffness", path, "compliance"),
        stiffness_ratio=_pos(comp, "stiffness_ratio", path, "compliance"),
        theta_max=np.deg2rad(_pos(ws, "theta_max_deg", path, "workspace")),
        motor_min=np.deg2rad(float(ws.get("motor_min_deg", -150.0))),
        motor_max=np.deg2rad(float(ws.get("motor_max_deg", 60.0))),
        sigma_mm=_pos(tr, "sigma_mm", path, "tracker"),
    )


@lru_cache(maxsize=1)
def default_geometry() -> Geometry:
    """The built-in machine's geometry (cached)."""
    return load_geometry()
