"""The result of a discrepancy diagnosis (:func:`pmcal.calib.ocpm.diagnose.diagnose`) and its JSON form
(docs/formats.md, "Diagnosis JSON"). Units: mm, effect values as in the vocabulary."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pmcal.mechanism.ocpm.data import Measurements
from pmcal.mechanism.ocpm.effects import VOCABULARY, effect_of_key
from pmcal.calib.ocpm.effect_values import EffectValue
from pmcal.mechanism.ocpm.params import LOG_RATIO
from pmcal.calib.ocpm.linear_tests import Linearization
from pmcal.calib.ocpm.noise_estimate import NoiseEstimate
from pmcal.mechanism.ocpm.params import is_angular
from pmcal.calib.solvers.result import IdentResult


#: scoreboard verdicts of a candidate that is significant but not named (the verdict sentence says so)
UNNAMED_SIGNIFICANT = ("explains only part of the structure", "not confirmed on held-out poses",
                       "implausible value", "too small")


@dataclass
class Candidate:
    """One row of the scoreboard (the state when the diagnosis ended, or when the effect was named)."""

    name: str
    available: bool
    reason: str = ""                      # why not available / verdict explanation
    survival: float = float("nan")        # fraction of a typical signature the baseline cannot absorb
    power_typical: float = float("nan")   # chance to detect it at a typical size with this campaign
    delta_chi2: float = float("nan")
    nu: float = float("nan")              # directions tested
    share: float = float("nan")           # share of the structure beyond the noise it explains
    F: float = float("nan")
    p_value: float = float("nan")
    threshold: float = float("nan")
    value: EffectValue | None = None
    cv_folds: int = 0
    held_out_share: float = float("nan")  # share of the held-out structure beyond the noise it removes
    transfer_share: float = float("nan")  # the same with whole workspace regions held out
    held_out_band: object = None          # held_out_test.HeldOutBand: the share's bands if true / if not
    motor_bands: dict = field(default_factory=dict)   # motor -> HeldOutBand of that motor's part alone
    motor_p_values: dict = field(default_factory=dict)  # motor -> p of that motor's part in the named model
    detectable_90: float = float("nan")   # smallest size detected with probability 0.9 (value's unit)
    verdict: str = "not tested"
    fix: str = ""


@dataclass
class Omnibus:
    """Is anything left beyond the noise? ratio: residual variance / sigma^2; robust_ratio: the same
    from medians of per-pose sums; excess_mm: RMS of what is left beyond the noise."""

    ratio: float
    robust_ratio: float
    p_value: float
    excess_mm: float
    structure: bool


@dataclass
class Diagnosis:
    effect: str | None
    effects: list[str]
    gap_before: float
    gap_after: float
    noise: NoiseEstimate
    verdict: str                          # "noise", "named", "unexplained", "named+unexplained"
    unexplained: bool
    notes: list[str]
    candidates: dict[str, Candidate]
    named: list[EffectValue]
    baseline: IdentResult
    final: IdentResult
    omnibus_before: Omnibus
    omnibus_after: Omnibus
    time_unit: str
    meas: Measurements
    lin_before: Linearization
    lin_after: Linearization
    cv_before: np.ndarray                 # (N, k, 3) held-out residuals, mm
    cv_after: np.ndarray
    folds: np.ndarray
    runtime_s: float = 0.0
    added_variable: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    unexplained_context: list = field(default_factory=list)   # residual_context.ContextLink, strongest first
    extrapolated: list[str] = field(default_factory=list)     # pose ids left out of the held-out gaps
    gap_before_all: float = float("nan")                      # the held-out gaps over every pose, mm
    gap_after_all: float = float("nan")

    @property
    def noise_floor(self) -> float:
        return self.noise.sigma_mm

    @property
    def found_unnamed(self) -> list[Candidate]:
        """Candidates significant at their threshold but not named (rejected for a reason the scoreboard
        gives), most significant first: what a verdict must not call "no missing effect"."""
        found = [c for c in self.candidates.values()
                 if c.verdict in UNNAMED_SIGNIFICANT and np.isfinite(c.p_value) and c.p_value < c.threshold]
        return sorted(found, key=lambda c: c.p_value)

    def params(self) -> dict[str, float]:
        """Geometric parameters of the final model, interface units (mm, deg)."""
        return {k: float(np.rad2deg(v)) if is_angular(k) else float(v)
                for k, v in zip(self.final.names, self.final.x) if effect_of_key(k) in (None, "overconstraint")
                and k != LOG_RATIO}

    def to_json(self) -> dict:
        """The diagnosis JSON document (docs/formats.md, "Diagnosis JSON")."""
        def val(e: EffectValue) -> dict:
            return {"name": e.name, "value": _num(e.value), "interval": [_num(v) for v in e.interval],
                    "unit": e.unit, "layer": VOCABULARY[e.name].layer, "member": e.member or None,
                    "member_params": {k: {"value": _num(v), "std": _num(s)} for k, (v, s) in e.member_params.items()},
                    "params": {k: {"value": _num(v), "std": _num(s)} for k, (v, s) in e.params.items()},
                    "motors": list(e.motors), "per_motor": [_jsonable(m) for m in e.per_motor],
                    "parts": [{"parts": p["parts"], "rate": _num(p["rate"]), "std": _num(p["std"]),
                               "separable": p["separable"]} for p in e.parts]}

        cands = []
        for c in self.candidates.values():
            cands.append({"name": c.name, "verdict": c.verdict, "reason": c.reason, "available": c.available,
                          "survival": _num(c.survival), "power_at_typical_size": _num(c.power_typical),
                          "delta_chi2": _num(c.delta_chi2), "directions": _num(c.nu), "F": _num(c.F),
                          "share_of_structure": _num(c.share), "held_out_share": _num(c.held_out_share),
                          "transfer_share": _num(c.transfer_share),
                          "held_out_test": c.held_out_band.to_json() if c.held_out_band is not None else None,
                          "held_out_test_per_motor": {str(m): b.to_json() for m, b in c.motor_bands.items()},
                          "p_value_per_motor": {str(m): _num(p) for m, p in c.motor_p_values.items()},
                          "detectable_at_90": _num(c.detectable_90),
                          "p_value": _num(c.p_value), "threshold": _num(c.threshold),
                          "value": val(c.value) if c.value else None, "cv_folds_selected": c.cv_folds,
                          "folds": int(self.folds.max() + 1) if self.folds.size else 0,
                          "fix": c.fix})
        return {
            "effect": self.effect, "effects": self.effects, "gap_before": self.gap_before,
            "gap_after": self.gap_after, "unit": "mm", "noise_floor": self.noise_floor,
            "extrapolated_poses": self.extrapolated, "gap_before_all_poses": _num(self.gap_before_all),
            "gap_after_all_poses": _num(self.gap_after_all),
            "verdict": self.verdict, "unexplained": self.unexplained, "notes": self.notes,
            "significant_unnamed": [{"name": c.name, "p_value": _num(c.p_value), "verdict": c.verdict,
                                     "reason": c.reason} for c in self.found_unnamed],
            "unexplained_context": [{"context": c.context, "share": _num(c.share), "p_value": _num(c.p_value),
                                     "direction": c.direction} for c in self.unexplained_context],
            "named": [val(e) for e in self.named],
            "noise": {"sigma_mm": self.noise.sigma_mm, "source": self.noise.source,
                      "model_free_mm": self.noise.free_mm, "model_free_robust_mm": self.noise.free_robust_mm,
                      "model_free_dof": self.noise.dof, "repeat_mm": self.noise.repeat_mm},
            "omnibus": {"before": vars(self.omnibus_before), "after": vars(self.omnibus_after)},
            "candidates": cands,
            "baseline": {"keys": [k for k in self.baseline.names], "chi2_per_dof": self.baseline.info["chi2_per_dof"],
                         "stiffness_ratio": self.baseline.info["stiffness_ratio"], "n_poses": len(self.meas)},
            "model": {"params": self.params(), "stiffness_ratio": self.final.info["stiffness_ratio"],
                      "effects": {e.name: _num(e.value) for e in self.named},
                      "chi2_per_dof": self.final.info["chi2_per_dof"]},
            "time_unit": self.time_unit, "runtime_s": self.runtime_s,
        }


def _jsonable(d: dict) -> dict:
    """A per-motor value dict with numbers JSON-ready (intervals as lists)."""
    return {k: ([_num(x) for x in v] if isinstance(v, (tuple, list)) else v if k == "motor" else _num(v))
            for k, v in d.items()}


def _num(v):
    if v is None:
        return None
    v = float(v)
    return v if np.isfinite(v) else None


