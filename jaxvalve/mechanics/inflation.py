"""The inflation limit of a membrane material: the most pressure a balloon of it holds.

A spherical balloon of reference radius R0 and thickness H, stretched equibiaxially by
lambda, holds the pressure

    P(lambda) = H w'(lambda) / (R0 lambda^2),

w(lambda) the material's strain energy per reference volume at C = lambda^2 I (virtual
work: the strain energy 4 pi R0^2 H w against the pressure's work on the volume
4/3 pi R0^3 lambda^3).  Where P (lambda) has a maximum, no equilibrium exists above it and
the balloon inflates without end: neo-Hookean, P R0 / H = 2 mu (1/lambda - 1/lambda^7),
peaks at lambda = 7^(1/6) with 1.2394 mu; the linear springs of `MassSpring` (three to a
triangle, w = 3/2 E (lambda - 1)^2) peak at lambda = 2 with 3 E / 4.  A material that
stiffens enough (St.Venant-Kirchhoff, Gent with a small Jm) has no maximum: P grows until
the stretch limit, and such a balloon has an equilibrium at every pressure.

`inflation_limit` finds the first maximum of P R0 numerically from the material's own
`energy_density` (so every model, and every parameter set, is covered by one
computation).  `InflationLimit.radius` turns an observed limit pressure into the
reference radius of the balloon that would peak there: the size of the bulge the limit
point implies, to compare with the valve's (a leaflet's belly, a few mm to about 10 mm).

A material that stiffens under inflation may instead lose its stiffness in compression:
`compression_limit` finds the stretch below 1 at which its uniaxial compressive stress
(lateral stress free) stops growing in magnitude.  St.Venant-Kirchhoff has one at
1/sqrt(3) (its nominal stress E_Y lam (lam^2 - 1) / 2); compressed further a triangle's
own stiffness is negative.  The soft StVK valves' limit points have states compressed
past it, and so do some of their equilibria (docs/limit-points.md).
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ParameterError, check_positive
from .materials import SpringGeometry
from .problem import MMHG

__all__ = ["InflationLimit", "balloon_pressure", "inflation_limit", "compression_limit",
           "uniaxial_stress"]


def _one_triangle_geometry():
    """`SpringGeometry` of an equilateral triangle whose first edge lies along the fibres."""
    ang = np.radians([0.0, 60.0, 120.0])
    unit = np.stack([np.cos(ang), np.sin(ang)], axis=-1)[None]          # (1, 3, 2)
    return SpringGeometry(unit=jnp.asarray(unit), cos2=jnp.asarray(np.cos(ang)[None] ** 2))


def _cauchy_green(stretch):
    """C = stretch^2 I (1, 2, 2): an equibiaxial stretch of one triangle."""
    return stretch**2 * jnp.eye(2, dtype=stretch.dtype)[None]


@jax.jit
def _curve(material, stretch):
    """(w'(lambda) (MPa), admissible) at each stretch (K,); material a pytree (traced)."""
    geom = _one_triangle_geometry()
    dw = jax.vmap(jax.grad(lambda s: material.energy_density(_cauchy_green(s), geom)[0]))
    ok = jax.vmap(lambda s: material.stretch_ok(_cauchy_green(s))[0])
    return dw(stretch), ok(stretch)


def balloon_pressure(material, thickness: float, stretch) -> np.ndarray:
    """P R0 (MPa mm = N/mm) of a spherical balloon of ``material`` at equibiaxial stretch
    ``stretch`` (array, > 1), thickness (mm); nan past the material's stretch limit."""
    h = check_positive("thickness", thickness, "mm")
    lam = np.atleast_1d(np.asarray(stretch, float))
    dw, ok = _curve(material, jnp.asarray(lam, dtype=jnp.float64))
    out = h * np.asarray(dw, float) / lam**2
    return np.where(np.asarray(ok) & np.isfinite(out), out, np.nan)


@dataclasses.dataclass(frozen=True)
class InflationLimit:
    """The peak of a balloon's pressure-stretch curve, or its absence.

    model: the material's name.  stretch: the equibiaxial stretch at the peak (None: P R0
    grows up to ``stretch_max`` or the stretch limit, no inflation limit).  pr: P R0 at
    the peak (MPa mm = N/mm; None without a peak).  stretch_max: how far it was searched."""

    model: str
    stretch: float | None
    pr: float | None
    stretch_max: float

    @property
    def exists(self) -> bool:
        return self.pr is not None

    def pressure(self, radius: float) -> float:
        """P_max (mmHg) of a balloon of reference radius ``radius`` (mm)."""
        r = check_positive("radius", radius, "mm")
        return self.pr / r / MMHG if self.exists else float("inf")

    def radius(self, pressure: float) -> float:
        """The reference radius (mm) of the balloon whose limit is ``pressure`` (mmHg)."""
        p = check_positive("pressure", pressure, "mmHg")
        return self.pr / (p * MMHG) if self.exists else float("nan")

    def describe(self, pressure: float | None = None) -> str:
        """One line: the peak (or why there is none), and with ``pressure`` (mmHg, an
        observed limit point) the bulge radius that would explain it."""
        if not self.exists:
            return (f"{self.model} stiffens: a balloon of it holds every pressure (P R0 grows "
                    f"up to a stretch of {self.stretch_max:.3g}), so the material has no "
                    "inflation limit")
        s = (f"a {self.model} balloon peaks at a stretch of {self.stretch:.3f} with "
             f"P R0 = {self.pr:.4g} N/mm")
        if pressure is not None:
            s += (f": a limit at {pressure:.3g} mmHg is that of a bulge of reference "
                  f"radius {self.radius(pressure):.2f} mm")
        return s


def inflation_limit(material, thickness: float, stretch_max: float = 8.0,
                    n: int = 2000) -> InflationLimit:
    """The first maximum of `balloon_pressure` over stretches 1 < lambda <= stretch_max
    (a grid of n points, refined by a bounded scalar search), or none.  ``material`` a
    validated `jaxvalve.mechanics.materials` model with concrete parameters."""
    from scipy.optimize import minimize_scalar
    h = check_positive("thickness", thickness, "mm")
    if not (np.isfinite(stretch_max) and stretch_max > 1.0):
        raise ParameterError(f"inflation_limit: stretch_max must be > 1; got {stretch_max}")
    material.validate()
    name = getattr(material, "name", type(material).__name__)
    lam = np.linspace(1.0, float(stretch_max), int(n))[1:]
    g = balloon_pressure(material, h, lam)
    valid = np.isfinite(g)
    if not valid.any():
        raise ParameterError(f"inflation_limit: {name} has no admissible stretch above 1")
    last = int(np.flatnonzero(valid)[-1])
    # the first grid point that beats both neighbours (a plateau counts at its start)
    peaks = np.flatnonzero((g[1:last] > g[:last - 1]) & (g[1:last] >= g[2:last + 1])) + 1
    if not len(peaks):
        return InflationLimit(name, None, None, float(lam[last]))
    i = int(peaks[0])
    res = minimize_scalar(lambda s: -float(balloon_pressure(material, h, s)[0]),
                          bounds=(lam[i - 1], lam[i + 1]), method="bounded",
                          options=dict(xatol=1e-10))
    return InflationLimit(name, float(res.x), float(-res.fun), float(stretch_max))


# ------------------------------------------------------------------ compression limit
def _biaxial(l1, l2):
    """C = diag(l1^2, l2^2) (1, 2, 2): one triangle stretched by l1 along its first edge
    (the fibres) and l2 across."""
    return jnp.stack([jnp.stack([l1**2, 0.0 * l1]), jnp.stack([0.0 * l1, l2**2])])[None]


@jax.jit
def _uniaxial(material, l1, l2):
    """(dw/dl1, dw/dl2, admissible) at each (l1, l2) (K,): the energy density's partials."""
    geom = _one_triangle_geometry()

    def w(a, b):
        return material.energy_density(_biaxial(a, b), geom)[0]
    ok = jax.vmap(lambda a, b: material.stretch_ok(_biaxial(a, b))[0])(l1, l2)
    return jax.vmap(jax.grad(w, 0))(l1, l2), jax.vmap(jax.grad(w, 1))(l1, l2), ok


#: The bracket of `uniaxial_stress`'s bisection for the free lateral stretch.
_LATERAL = (0.01, 10.0)


def uniaxial_stress(material, stretch, n_iter: int = 60) -> np.ndarray:
    """The nominal stress (MPa) of ``material`` stretched by ``stretch`` (array) along its
    first axis with the lateral stress free: dw/dl1 at the lateral stretch that zeroes
    dw/dl2 (bisection on 0.01-10; a lateral stretch past the material's stretch limit
    counts as too small below 1 and too large above); nan where that state is past it, or
    where no lateral stretch in 0.01-10 frees it."""
    lam = np.atleast_1d(np.asarray(stretch, float))
    if not (lam.size and np.all(np.isfinite(lam)) and np.all(lam > 0)):
        raise ParameterError(f"uniaxial_stress: every stretch must be finite and > 0; got "
                             f"{np.asarray(stretch).tolist()}")
    material.validate()
    l1 = jnp.asarray(lam)
    lo, hi = np.full(l1.shape, _LATERAL[0]), np.full(l1.shape, _LATERAL[1])
    for _ in range(n_iter):              # dw/dl2 rises through 0 at the free lateral stretch
        mid = 0.5 * (lo + hi)
        _, g, ok = (np.asarray(a) for a in _uniaxial(material, l1, jnp.asarray(mid)))
        low = np.where(ok, g < 0, mid < 1.0)
        lo, hi = np.where(low, mid, lo), np.where(low, hi, mid)
    l2 = 0.5 * (lo + hi)
    s, _, ok = (np.asarray(a) for a in _uniaxial(material, l1, jnp.asarray(l2)))
    free = (l2 > 1.01 * _LATERAL[0]) & (l2 < 0.999 * _LATERAL[1])   # not pinned at an end
    return np.where(ok & free, s, np.nan)


def compression_limit(material, stretch_min: float = 0.05, n: int = 2000) -> float | None:
    """The stretch below 1 at which the material's uniaxial compressive stress (lateral
    stress free, `uniaxial_stress`) stops growing in magnitude as it is compressed further
    (the largest stretch where d(stress)/d(stretch) turns negative on a grid of n points
    down to ``stretch_min``), or None where it keeps growing.  There the material's own
    stiffness is negative and a compressed element can collapse: St.Venant-Kirchhoff at
    1/sqrt(3) (S = E_Y E_11 in uniaxial stress for any nu, so the nominal stress is
    E_Y lam (lam^2 - 1) / 2); neo-Hookean, Gent and springs have none."""
    if not (np.isfinite(stretch_min) and 0.0 < stretch_min < 1.0):
        raise ParameterError(f"compression_limit: stretch_min must lie in (0, 1); got "
                             f"{stretch_min}")
    if int(n) < 3:
        raise ParameterError(f"compression_limit: n must be at least 3 grid points; got {n}")
    lam = np.linspace(1.0, float(stretch_min), int(n))
    s = uniaxial_stress(material, lam)
    bad = np.flatnonzero(~np.isfinite(s))         # past the stretch limit: search above it
    if len(bad):
        lam, s = lam[:bad[0]], s[:bad[0]]
    falling = np.flatnonzero(np.diff(s) >= 0)      # compressing further no longer lowers it
    if not len(falling):
        return None
    i = int(falling[0])
    # refine on the stiffness's root between the two grid points around the turn
    from scipy.optimize import brentq
    h = 1e-6

    def stiff(x):
        return float(np.diff(uniaxial_stress(material, [x - h, x + h]))[0] / (2 * h))
    a, b = lam[i + 1], lam[max(i - 1, 0)]
    if stiff(a) * stiff(b) > 0:
        return float(lam[i])
    return float(brentq(stiff, a, b, xtol=1e-10))
