"""Membrane strain energies, kept apart from assembly (scikit-fem style).

Every model is a frozen dataclass pytree whose float fields are traced parameters (changing
them never recompiles).  ``energy_density(C, geom)`` takes C (M, 2, 2), the right
Cauchy-Green tensor of each triangle's map from its flat reference, and returns the strain
energy per unit reference VOLUME (MPa = N mm / mm^3), shape (M,).  Element energy is
``H * A_T * W``; nodal forces are ``-grad`` of the total (paper eq. 2.5).  ``geom`` carries the
reference edge directions that the spring model needs (`SpringGeometry`).
"""
from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..contact.barrier import barrier
from ..errors import ParameterError


def _pytree(cls):
    cls = dataclasses.dataclass(frozen=True)(cls)
    fields = [f.name for f in dataclasses.fields(cls) if not f.metadata.get("static")]
    meta = [f.name for f in dataclasses.fields(cls) if f.metadata.get("static")]
    return jax.tree_util.register_dataclass(cls, data_fields=fields, meta_fields=meta)


def static_field(**kw):
    return dataclasses.field(metadata={"static": True}, **kw)


def _check_positive(name, value, model):
    v = np.asarray(value, dtype=float)
    if not np.all(np.isfinite(v)):
        raise ParameterError(f"{model}: {name} must be finite; got {value}")
    if np.any(v <= 0):
        raise ParameterError(f"{model}: {name} must be > 0 (MPa or dimensionless); got {value}")


def _concrete(x):
    """True when x is a concrete value (validation is skipped for tracers)."""
    return not isinstance(x, jax.core.Tracer)


def _safe_positive(v, eps=1e-300):
    """(v_safe, ok): v where v > eps, else 1; gradients stay finite (jax-md safe_mask)."""
    ok = v > eps
    return jnp.where(ok, v, 1.0), ok


def invariants(C):
    """2D invariants: trace (M,) and determinant (M,) of C."""
    tr = C[..., 0, 0] + C[..., 1, 1]
    det = C[..., 0, 0] * C[..., 1, 1] - C[..., 0, 1] * C[..., 1, 0]
    return tr, det


def collapse_barrier(C, J_hat):
    """b (M,) = J_hat^2 B(J / J_hat) = -(J - J_hat)^2 ln(J / J_hat) for J = sqrt(det C)
    below J_hat, else 0 (exactly, with a zero gradient): the contact's IPC barrier
    (`jaxvalve.contact.barrier.barrier`) on the area ratio; +inf where det C <= 1e-300 (a
    triangle collapsed to a line).  Evaluated only when a triangle is below the threshold
    (`lax.cond`; both branches under vmap)."""
    _, det = invariants(C)

    def active(det):
        ok = det > 1e-300
        J = jnp.sqrt(jnp.where(ok, det, 1.0))
        return jnp.where(ok, J_hat * J_hat * barrier(J / J_hat), jnp.inf)

    return jax.lax.cond(jnp.any(det < J_hat * J_hat), active, jnp.zeros_like, det)


class Material:
    """Base class: subclasses define `energy_density` and `validate`."""

    name = "material"
    needs_springs = False

    def validate(self):
        return self

    def stiffest(self):
        """The same model at its largest tangent modulus; used only for stiffness bounds."""
        return self

    def limit_free(self):
        """The nearest model without a stretch limit (itself where it has none); the
        closure driver settles a start past the limit with it
        (`jaxvalve.valve.closure.admissible_start`)."""
        return self

    def stretch_margin(self, C):
        """Float (M,): positive where the state is admissible for this model (finite
        energy); here det C (a collapsed or inverted triangle has none)."""
        _, det = invariants(C)
        return det

    def stretch_ok(self, C):
        """Bool (M,): state admissible for this model (finite energy)."""
        return self.stretch_margin(C) > 0


@_pytree
class StVenantKirchhoff(Material):
    """St.Venant-Kirchhoff membrane (plane stress).  W = lam/2 tr(E)^2 + mu tr(E^2),
    E = (C - I)/2, lam = E nu/(1 - nu^2), mu = E/(2(1 + nu)).  Its nodal forces equal the
    paper's triangular biquadratic springs (eq. 2.6).  E in MPa, nu in (-1, 0.5]."""

    E: Any = 1.0
    nu: Any = 0.45
    name = "stvk"

    def validate(self):
        if _concrete(self.E):
            _check_positive("E", self.E, "St.Venant-Kirchhoff")
        if _concrete(self.nu):
            nu = np.asarray(self.nu, dtype=float)
            if not np.all(np.isfinite(nu)) or np.any(nu <= -1) or np.any(nu > 0.5):
                raise ParameterError(f"St.Venant-Kirchhoff: nu must lie in (-1, 0.5]; got {self.nu}")
        return self

    def lame(self):
        lam = self.E * self.nu / (1.0 - self.nu**2)
        mu = self.E / (2.0 * (1.0 + self.nu))
        return lam, mu

    def energy_density(self, C, geom=None):
        lam, mu = self.lame()
        Eg = 0.5 * (C - jnp.eye(2))
        trE = Eg[..., 0, 0] + Eg[..., 1, 1]
        trE2 = jnp.sum(Eg * jnp.swapaxes(Eg, -1, -2), axis=(-1, -2))
        return 0.5 * lam * trE**2 + mu * trE2

    def stretch_margin(self, C):
        return jnp.ones(C.shape[:-2], C.dtype)


@_pytree
class NeoHookean(Material):
    """Incompressible neo-Hookean membrane (paper eq. 3.1):
    W = mu/2 (I1 + 1/I2 - 3), I1 = tr C, I2 = det C (the thickness stretch is 1/sqrt(I2)).
    mu in MPa; the paper uses mu = E/3 (`NeoHookean.from_youngs`)."""

    mu: Any = 1.0 / 3.0
    name = "neo-hookean"

    @classmethod
    def from_youngs(cls, E):
        return cls(mu=E / 3.0)

    def validate(self):
        if _concrete(self.mu):
            _check_positive("mu", self.mu, "neo-Hookean")
        return self

    def energy_density(self, C, geom=None):
        tr, det = invariants(C)
        det_s, ok = _safe_positive(det)
        return jnp.where(ok, 0.5 * self.mu * (tr + 1.0 / det_s - 3.0), jnp.inf)


@_pytree
class Gent(Material):
    """Incompressible Gent membrane (paper eq. 3.2):
    W = -Jm mu/2 ln(1 - (I1 + 1/I2 - 3)/Jm).  mu in MPa, Jm > 0 dimensionless.
    Past the stretch limit (I1 + 1/I2 - 3 >= Jm) the energy is +inf and the gradient is
    masked to zero, so no NaN enters a solve; the solvers report the state as
    `RESULTS.stretch_limit`."""

    mu: Any = 1.0 / 3.0
    Jm: Any = 2.3
    name = "gent"

    @classmethod
    def from_youngs(cls, E, Jm=2.3):
        return cls(mu=E / 3.0, Jm=Jm)

    def validate(self):
        if _concrete(self.mu):
            _check_positive("mu", self.mu, "Gent")
        if _concrete(self.Jm):
            _check_positive("Jm", self.Jm, "Gent")
        return self

    def _arg(self, C):
        tr, det = invariants(C)
        det_s, ok = _safe_positive(det)
        return 1.0 - (tr + 1.0 / det_s - 3.0) / self.Jm, ok

    def energy_density(self, C, geom=None):
        arg, ok = self._arg(C)
        arg_s, ok2 = _safe_positive(arg)
        return jnp.where(ok & ok2, -0.5 * self.Jm * self.mu * jnp.log(arg_s), jnp.inf)

    def limit_free(self):
        """Neo-Hookean with the same mu: Gent's limit Jm -> infinity, and its small-strain
        behaviour (eq. 3.2 expands to eq. 3.1 in (I1 + 1/I2 - 3)/Jm)."""
        return NeoHookean(mu=self.mu)

    def stretch_margin(self, C):
        """min(det C, 1 - (I1 + 1/I2 - 3)/Jm): positive inside the stretch limit."""
        _, det = invariants(C)
        arg, _ = self._arg(C)
        return jnp.minimum(det, arg)


@_pytree
class SpringGeometry:
    """Reference data for spring models, per triangle edge k (opposite vertex k).

    ``unit`` (M, 3, 2): unit reference edge vectors in the local (template) frame.
    ``cos2`` (M, 3): cos^2 of the angle between each edge and the fibre direction.
    """

    unit: Any
    cos2: Any


def _piecewise_psi(eps, E1, E2, E3, b1, b2):
    """Energy per volume of a spring with tangent modulus E1 / E2 / E3 below b1 / between /
    above b2 (eq. 3.3, stress continuous).  psi(eps) = int_0^eps sigma."""
    s1 = jnp.minimum(eps, b1)
    s2 = jnp.clip(eps, b1, b2) - b1
    s3 = jnp.maximum(eps, b2) - b2
    sig1 = E1 * b1
    sig2 = sig1 + E2 * (b2 - b1)
    return (0.5 * E1 * s1**2
            + sig1 * s2 + 0.5 * E2 * s2**2
            + sig2 * s3 + 0.5 * E3 * s3**2)


@_pytree
class MassSpring(Material):
    """The paper's mass-spring model (eq. 2.3) as a spring energy.

    Each triangle T lends each of its edges a spring with k = E H A_T / L^2, so an edge
    shared by two triangles has k = E H A_ij / L^2 as in eq. 2.3.  Spring energy is
    H A_T psi(eps), eps = l/L - 1.  The modulus is piecewise in the strain (eq. 3.3):
    tangent moduli E1, E2, E3 (MPa) with breaks at eps = break1, break2 (stress continuous,
    so the force has no jump).  Anisotropy (eq. 2.4): each modulus is
    sqrt(Ef^2 cos^2(theta) + Ecf^2 sin^2(theta)), theta the angle between the spring and the
    fibre direction (a spring along the fibres gets Ef).  ``E*_cf`` default to the fibre
    values (isotropic): with them None, no mixing is traced.

    Collapse barrier: springs alone hardly resist a triangle's collapse (a triangle with an
    angle of a few degrees can be flattened onto its base, and turned over, while its edge
    lengths change only at second order), where the hinge's normal is undefined and every
    solver stalls (the stress suite's sliver mesh).  A triangle whose area ratio
    J = A / A_0 falls below `collapse_J` = 0.1 therefore gains the energy density E1 b(J),
    b(J) = -(J - 0.1)^2 ln(J / 0.1) (IPC's barrier, on the area ratio: zero with its first
    two derivatives at J = 0.1, infinite at J = 0), as a solid's volume term would resist
    it.  (The same barrier on J^2 is 20 times weaker at J = 0.05 and left a sliver
    collapsed at 3 mmHg.)  Above 0.1 the energy is the springs' alone, unchanged (the
    benchmark's closed spring valve keeps J >= 0.97, Table 4's softest cell at h = 1.5 mm
    J >= 0.70).

    Linear law (`MassSpring.linear`): E2 = E3 = None (and E2_cf = E3_cf = None) selects
    psi = E1 eps^2 / 2, with no strain breaks traced.  The choice is static (the pytree
    structure), so a linear scene never compiles the piecewise law; its energy and forces
    equal the piecewise law's with E1 = E2 = E3 to rounding (tested).  E2 and E3 are given
    together or not at all.
    """

    E1: Any = 1.0
    E2: Any = 1.0
    E3: Any = 1.0
    E1_cf: Any = None
    E2_cf: Any = None
    E3_cf: Any = None
    break1: Any = 0.175
    break2: Any = 0.3
    name = "mass-spring"
    needs_springs = True
    #: area ratio A / A_0 below which a triangle's collapse barrier acts
    collapse_J = 0.1

    @classmethod
    def linear(cls, E, E_cf=None):
        """The linear law psi = E eps^2 / 2 (E_cf: cross-fibre modulus, eq. 2.4)."""
        return cls(E1=E, E2=None, E3=None, E1_cf=E_cf)

    @property
    def is_linear(self) -> bool:
        """True (static) when only E1 (and E1_cf) are set: one modulus, no breaks."""
        return (self.E2 is None and self.E3 is None and self.E2_cf is None
                and self.E3_cf is None)

    def _check_structure(self):
        if (self.E2 is None) != (self.E3 is None):
            raise ParameterError("mass-spring: give E2 and E3 together (the moduli between "
                                 "and above the strain breaks), or neither for the linear "
                                 f"law; got E2={self.E2}, E3={self.E3}")
        if self.E2 is None and (self.E2_cf is not None or self.E3_cf is not None):
            raise ParameterError("mass-spring: E2_cf / E3_cf need E2 and E3 (the linear law "
                                 "has one modulus, E1 and E1_cf)")
        if self.E1 is None:
            raise ParameterError("mass-spring: E1 (MPa) must be given")

    def validate(self):
        self._check_structure()
        for name in ("E1", "E2", "E3", "E1_cf", "E2_cf", "E3_cf"):
            v = getattr(self, name)
            if v is not None and _concrete(v):
                _check_positive(name, v, "mass-spring")
        if _concrete(self.break1) and _concrete(self.break2):
            b1, b2 = float(self.break1), float(self.break2)
            if not (np.isfinite(b1) and np.isfinite(b2) and 0 <= b1 <= b2):
                raise ParameterError("mass-spring: strain breaks need 0 <= break1 <= break2; "
                                     f"got break1={self.break1}, break2={self.break2}")
        return self

    def stiffest(self):
        if self.is_linear:
            return self
        emax = lambda *v: None if v[0] is None else jnp.maximum(jnp.maximum(v[0], v[1]), v[2])
        ef = emax(self.E1, self.E2, self.E3)
        ecf = emax(self.E1_cf, self.E2_cf, self.E3_cf)
        return dataclasses.replace(self, E1=ef, E2=ef, E3=ef, E1_cf=ecf, E2_cf=ecf, E3_cf=ecf)

    def moduli(self, cos2):
        """Per-spring moduli (E1, E2, E3) from eq. 2.4; for the linear law (E1, E1, E1)."""
        def mix(ef, ecf):
            if ef is None:
                return mix(self.E1, self.E1_cf)
            if ecf is None:
                return ef * jnp.ones_like(cos2)
            return jnp.sqrt(ef**2 * cos2 + ecf**2 * (1.0 - cos2))
        return (mix(self.E1, self.E1_cf), mix(self.E2, self.E2_cf), mix(self.E3, self.E3_cf))

    def energy_density(self, C, geom: SpringGeometry):
        u = geom.unit  # (M,3,2)
        l2 = jnp.einsum("mki,mij,mkj->mk", u, C, u)  # (l/L)^2
        l2s, ok = _safe_positive(l2)
        eps = jnp.where(ok, jnp.sqrt(l2s), 0.0) - 1.0
        self._check_structure()
        barrier = self.E1 * collapse_barrier(C, self.collapse_J)
        if self.is_linear:   # static: no breaks traced
            E = self.moduli(geom.cos2)[0]
            return jnp.sum(0.5 * E * eps**2, axis=-1) + barrier
        E1, E2, E3 = self.moduli(geom.cos2)
        return (jnp.sum(_piecewise_psi(eps, E1, E2, E3, self.break1, self.break2), axis=-1)
                + barrier)

    def stretch_margin(self, C):
        return jnp.ones(C.shape[:-2], C.dtype)


MODELS = {"stvk": StVenantKirchhoff, "neo-hookean": NeoHookean, "gent": Gent,
          "mass-spring": MassSpring}
