"""Design targets on coaptation metrics: bounds or set values, parsed from text or TOML.

A `Target` says what one metric should be: ``lower <= m``, ``m <= upper`` (either or both),
or ``m == value``.  Its penalty is ``weight * (violation / scale)^2`` (scale in the metric's
unit), zero inside the bounds, so a design that meets every target costs nothing but its
leaflet size.  `parse_target("h_c>=4")`, `parse_target("h=8")`, `parse_target("4<=h_CC<=6")`.
"""
from __future__ import annotations

import dataclasses
import math
import re

import jax.numpy as jnp

from jaxvalve.errors import ParameterError

__all__ = ["METRICS", "Target", "parse_target", "targets_from_dict", "DEFAULT_TARGETS"]

#: metric name -> (load, key of `smooth_metrics`, factor, unit, description).  load "he"
#: is the effective-height pressure (3 mmHg), "closed" the closing pressure (80 mmHg),
#: "template" needs no closure at all.
METRICS = {
    "h_E": ("he", "h_e", 1.0, "mm", "effective height at the effective-height load"),
    "h_CC": ("closed", "h_cc", 1.0, "mm", "coaptation height 5 mm from the axis, pair mean"),
    "h_avr": ("closed", "h_avr_valve", 1.0, "mm", "zone area / free-edge length, mean"),
    "NCCA_pct": ("closed", "ncca_valve", 100.0, "%", "zone area / cusp area, mean"),
    "h": ("closed", "h", 1.0, "mm", "largest coaptation height over pairs and w"),
    "h_c": ("closed", "h_c", 1.0, "mm", "axial extent of the three-leaflet zone"),
    "area": ("template", None, 1.0, "mm^2", "area of the flat template (leaflet size)"),
}
_ALIASES = {k.lower(): k for k in METRICS} | {"ncca": "NCCA_pct", "h_cc": "h_CC",
                                              "he": "h_E", "h_e": "h_E"}


def metric_name(name: str) -> str:
    """The canonical metric name; raises `ParameterError` listing the known ones."""
    key = _ALIASES.get(str(name).strip().lower())
    if key is None:
        raise ParameterError(f"unknown metric {name!r}; known metrics: {', '.join(METRICS)}")
    return key


def _num(name, v):
    if v is None:
        return None
    try:
        v = float(v)
    except (TypeError, ValueError):
        raise ParameterError(f"target {name} must be a number; got {v!r}") from None
    if not math.isfinite(v):
        raise ParameterError(f"target {name} must be finite; got {v}")
    return v


@dataclasses.dataclass(frozen=True)
class Target:
    """metric (a key of METRICS); lower / upper bounds or a set value (metric units);
    weight (> 0) and scale (> 0, metric units) of the quadratic penalty."""

    metric: str
    lower: float | None = None
    upper: float | None = None
    value: float | None = None
    weight: float = 1.0
    scale: float = 1.0

    def __post_init__(self):
        object.__setattr__(self, "metric", metric_name(self.metric))
        for f in ("lower", "upper", "value", "weight", "scale"):
            object.__setattr__(self, f, _num(f"{self.metric} {f}", getattr(self, f)))
        if self.value is not None and (self.lower is not None or self.upper is not None):
            raise ParameterError(f"target on {self.metric}: give a set value or bounds, "
                                 "not both")
        if self.value is None and self.lower is None and self.upper is None:
            raise ParameterError(f"target on {self.metric} needs a lower bound, an upper "
                                 "bound or a set value")
        if self.lower is not None and self.upper is not None and self.lower > self.upper:
            raise ParameterError(f"target on {self.metric} is contradictory: lower bound "
                                 f"{self.lower} > upper bound {self.upper}")
        for f in ("weight", "scale"):
            if getattr(self, f) is None or getattr(self, f) <= 0:
                raise ParameterError(f"target {self.metric} {f} must be > 0; "
                                     f"got {getattr(self, f)}")

    @property
    def load(self) -> str:
        return METRICS[self.metric][0]

    def penalty(self, m):
        """weight * (violation / scale)^2 of the metric value m (float or traced)."""
        if self.value is not None:
            v = m - self.value
        else:
            v = 0.0 * m
            if self.lower is not None:
                v = v + jnp.maximum(self.lower - m, 0.0)
            if self.upper is not None:
                v = v + jnp.maximum(m - self.upper, 0.0)
        return self.weight * (v / self.scale) ** 2

    def describe(self) -> str:
        unit = METRICS[self.metric][3]
        if self.value is not None:
            s = f"{self.metric} = {self.value:g} {unit}"
        elif self.lower is not None and self.upper is not None:
            s = f"{self.lower:g} <= {self.metric} <= {self.upper:g} {unit}"
        elif self.lower is not None:
            s = f"{self.metric} >= {self.lower:g} {unit}"
        else:
            s = f"{self.metric} <= {self.upper:g} {unit}"
        return s if self.weight == 1.0 else f"{s} (weight {self.weight:g})"

    def as_dict(self) -> dict:
        return {k: v for k, v in dataclasses.asdict(self).items() if v is not None}


_NUM = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
_NAME = r"[A-Za-z_][A-Za-z_0-9]*"


def parse_target(text: str, weight: float = 1.0) -> Target:
    """'h_c>=4', 'h<=9', 'h=8', '4<=h_CC<=6' (spaces allowed; units are the metric's)."""
    s = str(text).replace(" ", "")
    m = re.fullmatch(rf"({_NUM})<=({_NAME})<=({_NUM})", s)
    if m:
        return Target(m[2], lower=m[1], upper=m[3], weight=weight)
    m = re.fullmatch(rf"({_NAME})(>=|<=|==|=)({_NUM})", s)
    if not m:
        raise ParameterError(f"cannot read target {text!r}: write METRIC>=X, METRIC<=X, "
                             f"METRIC=X or X<=METRIC<=Y, METRIC one of {', '.join(METRICS)}")
    name, op, v = m[1], m[2], m[3]
    if op == ">=":
        return Target(name, lower=v, weight=weight)
    if op == "<=":
        return Target(name, upper=v, weight=weight)
    return Target(name, value=v, weight=weight)


def targets_from_dict(d: dict) -> tuple:
    """Targets from a TOML table ``{metric: {lower=.., upper=.., value=.., weight=..}}``
    or ``{metric: "expression"}``; raises `ParameterError` on unknown keys."""
    out = []
    for name, spec in d.items():
        if isinstance(spec, str):
            t = parse_target(spec)
            if t.metric != metric_name(name):
                raise ParameterError(f"target {name!r}: the expression {spec!r} is about "
                                     f"{t.metric}")
            out.append(t)
            continue
        if not isinstance(spec, dict):
            raise ParameterError(f"target {name!r} must be a table or an expression string")
        bad = set(spec) - {"lower", "upper", "value", "weight", "scale"}
        if bad:
            raise ParameterError(f"target {name!r}: unknown keys {sorted(bad)}; allowed: "
                                 "lower, upper, value, weight, scale")
        out.append(Target(name, **spec))
    return tuple(out)


#: The default design goal: central coaptation height of at least 4 mm and a maximal
#: coaptation height near 8 mm, with the smallest leaflet that achieves them.
DEFAULT_TARGETS = (Target("h_c", lower=4.0), Target("h", value=8.0))
