"""The planar machine's configuration (``mjcf/planar_2dof/machine.toml``), read and validated.

Every problem raises :class:`pmcal.errors.InputError` naming the file and the ``[section] key``.
Units in the file: mm and degrees; the returned objects follow :mod:`pmcal.calib.planar` (mm, radians).
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np

from pmcal.mechanism.planar.region import Region
from pmcal.mechanism.planar.geometry import ERROR_KEYS, Errors, Geometry, Workspace
from pmcal.mechanism.planar.noise import Noise, scale_sigma, servo_sigma
from pmcal.errors import InputError
from pmcal.mjcf import machine_dir

MACHINE_DIR = machine_dir("planar_2dof")
MODEL_XML = MACHINE_DIR / "planar_2dof.xml"
SCENE_XML = MACHINE_DIR / "scene.xml"
CONFIG_TOML = MACHINE_DIR / "machine.toml"


@dataclass(frozen=True)
class CalibrationSettings:
    """Paper sections 5-6: positions per boundary, eq. 31 threshold, eq. 32 threshold (rad), loop length."""

    n_per_boundary: int = 3
    eps0: float = 0.01
    mu0: float = math.radians(0.1)
    max_iterations: int = 19
    method: str = "tsvd"


@dataclass(frozen=True)
class DesignSettings:
    """Noise-optimal positions (this project): region, number of positions, method."""

    region: Region
    grid_step: float = 20.0
    positions: int = 6
    method: str = "gls"


@dataclass(frozen=True)
class PlanarMachine:
    """Everything machine.toml says (mm, rad)."""

    geometry: Geometry
    workspace: Workspace
    noise: Noise
    scale_range: float
    calibration: CalibrationSettings
    design: DesignSettings
    presets: dict[str, Errors]
    source: str = ""

    def preset(self, name: str) -> Errors:
        try:
            return self.presets[name]
        except KeyError:
            raise InputError(f"unknown preset '{name}' (known: {', '.join(self.presets)})",
                             field="--preset") from None


class _Reader:
    def __init__(self, doc: dict, path: str):
        self.doc, self.path = doc, path

    def _err(self, section: str, key: str, msg: str) -> InputError:
        return InputError(msg, file=self.path, field=f"[{section}] {key}")

    def section(self, name: str) -> dict:
        sec = self.doc.get(name)
        if not isinstance(sec, dict):
            raise InputError(f"missing section [{name}]", file=self.path, field=f"[{name}]")
        return sec

    def number(self, section: str, key: str, *, positive: bool = False, default=None) -> float:
        sec = self.section(section)
        if key not in sec:
            if default is not None:
                return float(default)
            raise self._err(section, key, "missing key")
        v = sec[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise self._err(section, key, f"must be a finite number, got {v!r}")
        if positive and v <= 0:
            raise self._err(section, key, f"must be positive, got {v}")
        return float(v)

    def vector(self, section: str, key: str, n: int = 2, *, positive: bool = False, default=None) -> np.ndarray:
        sec = self.section(section)
        if key not in sec:
            if default is not None:
                return np.asarray(default, dtype=float)
            raise self._err(section, key, "missing key")
        v = sec[key]
        if (not isinstance(v, list) or len(v) != n
                or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)
                           for x in v)):
            raise self._err(section, key, f"must be a list of {n} finite numbers, got {v!r}")
        out = np.asarray(v, dtype=float)
        if positive and np.any(out <= 0):
            raise self._err(section, key, f"must be positive, got {v}")
        return out

    def text(self, section: str, key: str, choices: tuple[str, ...], default: str) -> str:
        v = self.section(section).get(key, default)
        if v not in choices:
            raise self._err(section, key, f"must be one of {', '.join(choices)}, got {v!r}")
        return v


def load_machine(path: str | Path | None = None) -> PlanarMachine:
    """Read and validate a planar machine.toml (default: the built-in machine)."""
    path = Path(path) if path is not None else CONFIG_TOML
    p = str(path)
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError("file not found", file=p) from None
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise InputError(f"cannot read machine configuration ({exc})", file=p) from None
    rd = _Reader(doc, p)
    geom = Geometry(
        e=np.stack([rd.vector("geometry", "e1"), rd.vector("geometry", "e2")]),
        L=rd.vector("geometry", "L", positive=True), l=rd.vector("geometry", "l", positive=True),
        c=rd.vector("geometry", "c"), d=rd.vector("geometry", "d"),
        home=np.deg2rad(rd.vector("geometry", "home_deg")))
    if np.any(geom.l <= geom.L):
        raise InputError("distal links must be longer than the proximal links", file=p, field="[geometry] l")
    ws = Workspace(H=rd.number("workspace", "H", positive=True), b=rd.number("workspace", "b", positive=True),
                   h=rd.number("workspace", "h", positive=True))
    scale_range = rd.number("noise", "scale_range_mm", positive=True)
    noise = Noise(
        scale=scale_sigma(scale_range, rd.number("noise", "scale_base_error_um", positive=True)),
        servo=servo_sigma(rd.number("noise", "servo_pulses_per_rev", positive=True),
                          rd.number("noise", "servo_max_pulse_error", positive=True),
                          rd.number("noise", "reduction", positive=True)))
    n = rd.number("calibration", "n_per_boundary", positive=True)
    if n != int(n) or n < 3:
        raise InputError("must be an integer >= 3 (K = 2n > 5 positions, paper section 5)", file=p,
                         field="[calibration] n_per_boundary")
    max_it = rd.number("calibration", "max_iterations", positive=True)
    if max_it != int(max_it) or max_it < 2:
        raise InputError("must be an integer >= 2", file=p, field="[calibration] max_iterations")
    cal = CalibrationSettings(
        n_per_boundary=int(n), eps0=rd.number("calibration", "eps0", positive=True),
        mu0=math.radians(rd.number("calibration", "mu0_deg", positive=True)), max_iterations=int(max_it),
        method=rd.text("calibration", "method", ("tsvd", "ls", "gls"), "tsvd"))
    x, y = rd.vector("design", "x"), rd.vector("design", "y")
    for key, v in (("x", x), ("y", y)):
        if v[0] >= v[1]:
            raise InputError("must be [min, max] with min < max", file=p, field=f"[design] {key}")
    k = rd.number("design", "positions", positive=True)
    if k != int(k) or k < 6:
        raise InputError("must be an integer >= 6", file=p, field="[design] positions")
    design = DesignSettings(
        region=Region(x=(float(x[0]), float(x[1])), y=(float(y[0]), float(y[1])),
                      min_transmission=rd.number("design", "min_transmission", positive=True),
                      min_platform=rd.number("design", "min_platform", positive=True),
                      scale_range=scale_range),
        grid_step=rd.number("design", "grid_step", positive=True), positions=int(k),
        method=rd.text("design", "method", ("tsvd", "ls", "gls"), "gls"))
    presets = {}
    for name, values in doc.get("presets", {}).items():
        if not isinstance(values, dict):
            raise InputError("must be a table of error values", file=p, field=f"[presets.{name}]")
        for key, v in values.items():
            if key not in ERROR_KEYS:
                raise InputError(f"unknown error key (known: {', '.join(ERROR_KEYS)})", file=p,
                                 field=f"[presets.{name}] {key}")
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise InputError(f"must be a finite number, got {v!r}", file=p, field=f"[presets.{name}] {key}")
        presets[name] = Errors.from_interface(values)
    if "nominal" not in presets:
        presets["nominal"] = Errors()
    return PlanarMachine(geometry=geom, workspace=ws, noise=noise, scale_range=scale_range, calibration=cal,
                         design=design, presets=presets, source=p)


@lru_cache(maxsize=1)
def default_machine() -> PlanarMachine:
    """The built-in machine (cached)."""
    return load_machine()
