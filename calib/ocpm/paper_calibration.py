"""The paper's identification procedure (Sun et al. 2018, section IV): one problem per actuated limb
(eq. 14) solved by one of the paper's methods, with an identifiability analysis of each limb.

Internal units mm and rad; the parameter keys are those of :mod:`pmcal.mechanism.ocpm.params`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from pmcal.calib.ocpm.paper_model import PaperModel, errors_from_vector, explain, from_measurements
from pmcal.mechanism.ocpm.config import Geometry, default_geometry
from pmcal.mechanism.ocpm.params import ANGULAR_FIELDS, ErrorSet

@dataclass
class PaperCalibration:
    """Per-limb identification with the paper's model (internal units mm/rad).

    results : per limb, the solver's :class:`IdentResult` (parameters in the model's order).
    identifiability : per limb, analysis of the whitened Jacobian at the solution (measured poses).
    design : per limb, analysis on the nominal machine at the measured orientations (first order).
    """

    names: list[str]
    x: np.ndarray
    std: np.ndarray
    results: dict
    identifiability: dict
    design: dict
    model: PaperModel
    wall_time: float

    @property
    def unidentifiable(self) -> list[str]:
        return [k for a in self.design.values() for k in a.unidentifiable]

    def errors(self) -> ErrorSet:
        return errors_from_vector(self.names, self.x)

    def params(self) -> dict[str, float]:
        """Identified values in interface units (mm, deg), unidentifiable ones left out (nominal)."""
        return {k: _to_interface(k, v) for k, v in zip(self.names, self.x) if k not in self.unidentifiable}

    def uncertainty(self) -> dict[str, float | None]:
        """Cramér-Rao standard deviations in interface units; None where unidentifiable."""
        return {k: (None if not np.isfinite(s) else _to_interface(k, s)) for k, s in zip(self.names, self.std)}


def _to_interface(key: str, v: float) -> float:
    return float(np.rad2deg(v)) if key.split(".", 1)[1] in ANGULAR_FIELDS else float(v)


def calibrate(meas, method: str = "hga", limbs: tuple[int, ...] = (1, 2), *, seed: int | None = 0,
              sigma_mm: float | None = None, tilts: bool = False, planarity: bool = False,
              prior_std: np.ndarray | float | None = None, geom: Geometry | None = None,
              on_limb_done=None, **options) -> PaperCalibration:
    """The paper's procedure: one identification problem per actuated limb (eq. 14), solved by ``method``.

    ``on_limb_done(limb, result)`` is called after each limb (progress). ``options`` go to the solver.
    """
    from pmcal.calib.identifiability import analyse
    from pmcal.calib.solvers import identify

    t0 = time.perf_counter()
    geom = geom or default_geometry()
    names, xs, stds, results, ident, design = [], [], [], {}, {}, {}
    for j in limbs:
        m = from_measurements(meas, (j,), tilts, planarity, "noise", sigma_mm, geom)
        prob = m.problem()
        res = identify(prob, method, seed=seed, prior_std=prior_std, **options)
        design[j] = analyse(prob.design, explain=lambda k: explain(k, geom))
        ident[j] = analyse(prob.fix(res.fixed), res.x[[res.names.index(k) for k in res.names
                                                       if k not in res.fixed]],
                           explain=lambda k: explain(k, geom))
        std = res.std.copy()
        std[[res.names.index(k) for k in res.fixed]] = np.inf
        names += res.names
        xs.append(res.x)
        stds.append(std)
        results[j] = res
        if on_limb_done is not None:
            on_limb_done(j, res)
    model = from_measurements(meas, tuple(limbs), tilts, planarity, "noise", sigma_mm, geom)
    return PaperCalibration(names=names, x=np.concatenate(xs), std=np.concatenate(stds), results=results,
                            identifiability=ident, design=design, model=model,
                            wall_time=time.perf_counter() - t0)
