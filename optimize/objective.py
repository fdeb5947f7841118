"""The design objective: target penalties + leaflet size + template constraints.

    f(theta) = sum_k target_k.penalty(m_k(theta))                 (targets.py)
             + size_weight * area(theta) / area_ref               (smallest adequate leaflet)
             + constraint_weight * sum_c (max(0, margin - slack_c) / margin)^2

theta = (r, a, b) mm with alpha held fixed.  The constraint slacks (mm) are
2b - |AD| (template validity: E above the chord A-D) and 2b - d_cc (a free edge longer than
the distance between the leaflet's commissures).  Bounds on r, a, b are not penalised:
the loop projects onto them.  A template with a negative slack is infeasible, and the loop
never evaluates it.
"""
from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np

from jaxvalve.errors import ParameterError
from jaxvalve.geometry.template import template_area

from .targets import DEFAULT_TARGETS, METRICS, Target

__all__ = ["Objective", "DEFAULT_BOUNDS", "chord"]

#: Default box for (r, a, b) in mm: wide around adult aortic leaflets (Ozaki's sizer
#: spans 13-31 mm free edges; b is half the free edge).
DEFAULT_BOUNDS = {"r": (8.0, 16.0), "a": (2.0, 14.0), "b": (8.0, 22.0)}


def chord(r, a, alpha):
    """|AD| (mm) of the template, differentiable in r and a: 2 (r sin(alpha/2) + a
    cos(alpha/2)); alpha (degrees) is a fixed number."""
    beta = float(alpha) * (math.pi / 360.0)
    return 2.0 * (r * math.sin(beta) + a * math.cos(beta))


@dataclasses.dataclass(frozen=True)
class Objective:
    """targets: `Target`s; size_weight (>= 0) per unit of area / area_ref; area_ref (mm^2,
    > 0; the loop sets it to the start template's area when None); bounds: {name: (lo, hi)}
    in mm for r, a, b; margin (mm, > 0) and constraint_weight (> 0) of the constraint
    penalty."""

    targets: tuple = DEFAULT_TARGETS
    size_weight: float = 0.1
    area_ref: float | None = None
    bounds: dict = dataclasses.field(default_factory=lambda: dict(DEFAULT_BOUNDS))
    margin: float = 0.5
    constraint_weight: float = 100.0

    def __post_init__(self):
        ts = tuple(self.targets)
        if not all(isinstance(t, Target) for t in ts):
            raise ParameterError("targets must be Target objects (see optimize.parse_target)")
        object.__setattr__(self, "targets", ts)
        if not ts and self.size_weight == 0:
            raise ParameterError("the objective is empty: give a target or a size_weight > 0")
        for name, v, ok in (("size_weight", self.size_weight, lambda v: v >= 0),
                            ("margin", self.margin, lambda v: v > 0),
                            ("constraint_weight", self.constraint_weight, lambda v: v > 0)):
            if not (isinstance(v, (int, float)) and math.isfinite(v) and ok(v)):
                rng = ">= 0" if name == "size_weight" else "> 0"
                raise ParameterError(f"{name} must be a finite number {rng}; got {v!r}")
        if self.area_ref is not None and not (math.isfinite(self.area_ref) and self.area_ref > 0):
            raise ParameterError(f"area_ref must be a finite area > 0 mm^2; got {self.area_ref}")
        b = dict(DEFAULT_BOUNDS)
        for k, v in dict(self.bounds).items():
            if k not in DEFAULT_BOUNDS:
                raise ParameterError(f"bounds: unknown parameter {k!r}; the loop tunes r, a, b")
            try:
                lo, hi = (float(u) for u in v)
            except (TypeError, ValueError):
                raise ParameterError(f"bounds[{k!r}] must be (lower, upper) in mm; got {v!r}") from None
            if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo < hi):
                raise ParameterError(f"bounds[{k!r}] must satisfy 0 < lower < upper (mm); "
                                     f"got ({lo}, {hi})")
            b[k] = (lo, hi)
        object.__setattr__(self, "bounds", b)

    @property
    def loads(self) -> set:
        """The closures the targets need: subset of {'he', 'closed'}."""
        return {t.load for t in self.targets} - {"template"}

    @property
    def lower(self):
        return np.array([self.bounds[k][0] for k in "rab"])

    @property
    def upper(self):
        return np.array([self.bounds[k][1] for k in "rab"])

    def project(self, rab):
        """Clip (r, a, b) onto the bounds."""
        return np.clip(np.asarray(rab, float), self.lower, self.upper)

    def slacks(self, rab, alpha, d_cc):
        """{'validity': 2b - |AD|, 'free_edge': 2b - d_cc} (mm; negative = infeasible)."""
        r, a, b = rab[0], rab[1], rab[2]
        return {"validity": 2 * b - chord(r, a, alpha), "free_edge": 2 * b - d_cc}

    def terms(self, rab, alpha, metrics: dict, d_cc, area_ref):
        """Every term of f (jnp scalars): 'target:<metric>', 'size', 'constraint:<name>'.

        metrics: {metric name: value} (METRICS units), for every targeted metric except
        'area', which comes from rab here."""
        r, a, b = rab[0], rab[1], rab[2]
        area = template_area(r, a, b, alpha, jnp)
        out = {}
        for t in self.targets:
            m = area if t.metric == "area" else metrics[t.metric]
            key = f"target:{t.metric}"
            out[key] = out.get(key, 0.0) + t.penalty(m)
        out["size"] = self.size_weight * area / area_ref
        for name, s in self.slacks(rab, alpha, d_cc).items():
            out[f"constraint:{name}"] = self.constraint_weight * (
                jnp.maximum(self.margin - s, 0.0) / self.margin) ** 2
        return out

    def value(self, rab, alpha, metrics, d_cc, area_ref):
        return sum(self.terms(rab, alpha, metrics, d_cc, area_ref).values())

    def as_dict(self) -> dict:
        return dict(targets=[t.as_dict() for t in self.targets], size_weight=self.size_weight,
                    area_ref=self.area_ref, bounds={k: list(v) for k, v in self.bounds.items()},
                    margin=self.margin, constraint_weight=self.constraint_weight)

    @classmethod
    def from_dict(cls, d: dict) -> "Objective":
        d = dict(d)
        d["targets"] = tuple(Target(**t) for t in d.get("targets", ()))
        if "bounds" in d:
            d["bounds"] = {k: tuple(v) for k, v in d["bounds"].items()}
        return cls(**d)


def metric_units():
    return {k: v[3] for k, v in METRICS.items()}
