"""The flat Ozaki leaflet template (paper Fig. 2).

Template frame (mm): O = (0, 0) is the centre of the bottom arc, y points to the free
edge.  The arc B-C has radius r and subtends alpha (default 160 degrees) about the
downward direction; B = r(-sin beta, -cos beta), C = r(sin beta, -cos beta) with
beta = alpha / 2.  A and D continue B and C along the arc's tangent for length a:
A = B + a(-cos beta, sin beta), D = C + a(cos beta, sin beta).  The free edge A-E-D is two
segments of length b with E on the symmetry axis above the chord A-D:
E = (0, A_y + sqrt(b^2 - |AD|^2 / 4)).

    |AD| = 2 (r sin beta + a cos beta)
    sutured edge A-B-C-D: 2a + pi r alpha / 180
    free edge A-E-D:      2b

Valid only where r, a, b > 0, 0 < alpha <= 180 degrees (`ALPHA_RANGE`) and 2b > |AD|.  Every
coordinate here is a smooth function of (r, alpha, a, b), written with ``numpy``-compatible
operations so that the same formulas serve JAX tracing (see `outline`).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..errors import ParameterError

__all__ = ["Template", "PAPER_TEMPLATES", "ALPHA_RANGE"]


#: valid arc angles alpha (degrees), open below and closed above: (0, 180].  Above 180
#: degrees the arc B-C is more than a semicircle, so the tangent extensions A-B and C-D lean
#: towards each other and the template narrows above its arc, where the sinus's suture line
#: widens towards the commissures: placed in the benchmark root, from 160 degrees up such a
#: template is compressed the more, the larger alpha (smallest area ratio of a placed
#: triangle 0.78 at 160 degrees, 0.72 at 180, 0.68 at 200, 0.61 at 250; h = 1.5 mm).  Within the range
#: |AD| > 0 always holds.  The paper fixes alpha = 160.
ALPHA_RANGE = (0.0, 180.0)


@dataclasses.dataclass(frozen=True)
class Template:
    """Leaflet template parameters (mm, degrees); validated on construction."""

    r: float
    a: float
    b: float
    alpha: float = 160.0

    def __post_init__(self):
        for name in ("r", "a", "b", "alpha"):
            v = getattr(self, name)
            try:
                v = float(v)
            except (TypeError, ValueError):
                raise ParameterError(f"template {name} must be a number; got {v!r}") from None
            if not math.isfinite(v):
                raise ParameterError(f"template {name} must be finite; got {v}")
            object.__setattr__(self, name, v)
        for name in ("r", "a", "b"):
            if getattr(self, name) <= 0:
                raise ParameterError(f"template {name} must be > 0 mm; got {getattr(self, name)}")
        if not ALPHA_RANGE[0] < self.alpha <= ALPHA_RANGE[1]:
            raise ParameterError(
                f"template alpha must lie in ({ALPHA_RANGE[0]:g}, {ALPHA_RANGE[1]:g}] degrees "
                f"(past 180 the sides A-B and C-D lean towards each other, a template no "
                f"sinus scallop fits); got {self.alpha}")
        ad = self.chord
        if 2 * self.b <= ad:
            raise ParameterError(
                f"template b must exceed |AD| / 2 = {ad / 2:.3f} mm so that E lies above the "
                f"chord A-D (free edge 2b > |AD|); got b = {self.b} mm "
                f"(r = {self.r}, a = {self.a}, alpha = {self.alpha})")

    @property
    def _beta(self):
        return math.radians(self.alpha) / 2

    @property
    def chord(self) -> float:
        """|AD| (mm): distance between the free edge's end points."""
        return 2 * (self.r * math.sin(self._beta) + self.a * math.cos(self._beta))

    @property
    def sutured_length(self) -> float:
        """Length of A-B-C-D (mm): 2a + pi r alpha / 180."""
        return sutured_length(self.r, self.a, self.alpha)

    @property
    def free_length(self) -> float:
        """Length of A-E-D (mm): 2b."""
        return 2 * self.b

    @property
    def points(self) -> dict:
        """Corner points O, A, B, C, D, E (each (2,) mm) in the template frame."""
        return {k: np.asarray(v) for k, v in zip("OABCDE", corners(self.r, self.a, self.b,
                                                                     self.alpha, np))}

    @property
    def height(self) -> float:
        """Bottom of the arc to E (mm)."""
        return float(self.points["E"][1] + self.r)

    @property
    def area(self) -> float:
        """Area of the flat template (mm^2), exact (circular segment + polygon)."""
        return float(template_area(self.r, self.a, self.b, self.alpha))

    def as_dict(self):
        return dataclasses.asdict(self)


def sutured_length(r, a, alpha):
    """Length of A-B-C-D (mm): 2a + pi r alpha / 180 (plain arithmetic: floats or traced)."""
    return 2 * a + math.pi * r * alpha / 180.0


def template_area(r, a, b, alpha, xp=np):
    """Area (mm^2) of the template: the circular segment below B-C plus the pentagon
    B-C-D-E-A (counter-clockwise, so the shoelace sum is positive for a valid template).
    Pure formulas, differentiable with xp = jax.numpy."""
    _, A, B, C, D, E = corners(r, a, b, alpha, xp)
    beta = alpha * (math.pi / 360.0)
    segment = 0.5 * r * r * (2 * beta - xp.sin(2 * beta))
    poly = xp.stack([B, C, D, E, A])
    x, y = poly[:, 0], poly[:, 1]
    shoelace = 0.5 * (xp.sum(x * xp.roll(y, -1)) - xp.sum(y * xp.roll(x, -1)))
    return segment + shoelace


def corners(r, a, b, alpha, xp=np):
    """O, A, B, C, D, E of the template as (2,) arrays; ``xp`` = numpy or jax.numpy.

    Pure formulas (no validation), differentiable in (r, a, b, alpha) with xp = jax.numpy.
    """
    beta = alpha * (math.pi / 360.0)
    s, c = xp.sin(beta), xp.cos(beta)
    B = xp.stack([-r * s, -r * c])
    C = xp.stack([r * s, -r * c])
    A = B + a * xp.stack([-c, s])
    D = C + a * xp.stack([c, s])
    half = r * s + a * c
    E = xp.stack([0.0 * r, A[1] + xp.sqrt(b * b - half * half)])
    O = xp.stack([0.0 * r, 0.0 * r])
    return O, A, B, C, D, E


def sutured_point(t, r, a, alpha, xp=np):
    """Points on A-B-C-D at arc-length fractions t in [0, 1] (shape (K,) -> (K, 2))."""
    beta = alpha * (math.pi / 360.0)
    s, c = xp.sin(beta), xp.cos(beta)
    L_arc = 2 * beta * r
    L = 2 * a + L_arc
    u = t * L
    # A -> B
    A = xp.stack([-r * s - a * c, -r * c + a * s])
    seg1 = A[None, :] + u[:, None] * xp.stack([c, -s])[None, :]
    # B -> C along the arc: angle from the downward direction goes from -beta to +beta
    phi = -beta + (u - a) / r
    arc = xp.stack([r * xp.sin(phi), -r * xp.cos(phi)], axis=1)
    # C -> D
    C = xp.stack([r * s, -r * c])
    seg3 = C[None, :] + (u - a - L_arc)[:, None] * xp.stack([c, s])[None, :]
    return xp.where((u <= a)[:, None], seg1, xp.where((u <= a + L_arc)[:, None], arc, seg3))


def free_point(t, r, a, b, alpha, xp=np):
    """Points on A-E-D at arc-length fractions t in [0, 1] (shape (K,) -> (K, 2))."""
    _, A, _, _, D, E = corners(r, a, b, alpha, xp)
    u = 2 * t
    first = A[None, :] + u[:, None] * (E - A)[None, :]
    second = E[None, :] + (u - 1)[:, None] * (D - E)[None, :]
    return xp.where((u <= 1)[:, None], first, second)


# Paper Fig. 3.  Under the geometry above these fail 2b > |AD| (|AD| = 25.5, 28.2,
# 30.1 mm against 2b = 22, 26, 28 mm); kept as data so that the error can be shown.
PAPER_TEMPLATES = {"a": dict(r=11.0, a=11.0, b=11.0), "b": dict(r=12.0, a=13.0, b=13.0),
                   "c": dict(r=13.0, a=13.0, b=14.0)}
