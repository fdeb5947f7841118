"""Bending of a thin sheet: a discrete hinge energy (Grinspun et al. 2003, "discrete shells").

The specification models a leaflet as a membrane, which has no bending stiffness.  A membrane that
carries more length than it has room for (a free edge of 30 mm between commissures 22.5 mm
apart) then has zero-energy crumpling modes, and its folds sharpen to the mesh size: an
equilibrium solver stalls there.  Real pericardium is a plate of thickness H, with the
bending modulus

    D = E H^3 / (12 (1 - nu^2))   (N mm),

and a leaflet under pressure P bends only on the length scale (D / P)^(1/3): for E = 1 MPa,
H = 0.3 mm, nu = 0.45 this is 0.64 mm at P = 80 mmHg, below the mesh size (0.88 mm), but
1.9 mm at 3 mmHg, so the physical bending stiffness gives creases a finite width and
changes the low-pressure shape (h_E) by about a millimetre (docs/mechanics.md,
"Bending").  `Bending(scale)` adds ``scale`` times this physical D (scale = 0 switches it
off at no cost; `None` in `Params` skips it entirely).

Energy, over interior edges e with adjacent triangles T1, T2 (reference areas A1, A2,
reference length L_e) and current unit normals n1, n2 (dihedral angle theta_e):

    E_b = D sum_e (1 - n1 . n2) L_e^2 / (A1 + A2)   ~  (D / 2) sum_e theta_e^2 L_e^2 / (A1 + A2),

which tends to the plate energy (D / 2) \\int kappa^2 dA of a cylinder (within a few per
cent on refined structured and Delaunay meshes; tested).  The flat
template is the stress-free state, so the rest angle is zero.  A hinge folded past 160
degrees meets a barrier (`fold_barrier`, with the physical D whatever the bending scale):
the bending energy's force vanishes as a fold nears 180 degrees, and a crease pinched by
the pressure would otherwise fold through itself.  The effective small-strain
moduli per model: StVK (E, nu); neo-Hookean and Gent (3 mu, 1/2); mass-spring (E1, 1/3).
"""
from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ParameterError
from .materials import Gent, MassSpring, NeoHookean, StVenantKirchhoff, _concrete

__all__ = ["Bending", "hinges", "plate_modulus", "hinge_weights", "bending_energy",
           "fold_barrier", "FOLD_BARRIER_DEG"]


def hinges(triangles) -> np.ndarray:
    """Interior edges as hinges (K, 6) int32: (i, j, k, l, t1, t2), edge i-j, k opposite in
    triangle t1 that holds i->j, l opposite in triangle t2 that holds j->i."""
    tri = np.asarray(triangles, np.int64)
    m = tri.shape[0]
    rows = []
    for s in range(3):
        i, j, k = tri[:, s], tri[:, (s + 1) % 3], tri[:, (s + 2) % 3]
        rows.append(np.stack([i, j, k, np.arange(m)], axis=1))
    d = np.concatenate(rows)  # (3M, 4) directed edge i->j, opposite k, triangle
    n = int(tri.max()) + 1
    key = d[:, 0] * n + d[:, 1]
    rkey = d[:, 1] * n + d[:, 0]
    order = np.argsort(key)
    pos = np.clip(np.searchsorted(key[order], rkey), 0, len(key) - 1)
    match = key[order][pos] == rkey
    sel = match & (d[:, 0] < d[:, 1])  # each interior edge once
    other = order[pos[sel]]
    out = np.stack([d[sel, 0], d[sel, 1], d[sel, 2], d[other, 2], d[sel, 3], d[other, 3]],
                   axis=1)
    return out.astype(np.int32)


def plate_modulus(material, thickness):
    """D = E H^3 / (12 (1 - nu^2)) in N mm from the material's small-strain moduli (traced)."""
    if isinstance(material, StVenantKirchhoff):
        E, nu = material.E, material.nu
    elif isinstance(material, (NeoHookean, Gent)):
        E, nu = 3.0 * material.mu, 0.5
    elif isinstance(material, MassSpring):
        E, nu = material.E1, 1.0 / 3.0
    else:
        raise ParameterError(f"no plate modulus for material {type(material).__name__}")
    return E * thickness**3 / (12.0 * (1.0 - nu * nu))


def hinge_weights(ref, hinge):
    """L_e^2 / (A1 + A2) per hinge (K,), dimensionless, from the reference coordinates."""
    X = ref if ref.shape[1] == 3 else jnp.concatenate([ref, jnp.zeros_like(ref[:, :1])], 1)
    xi, xj, xk, xl = (X[hinge[:, c]] for c in range(4))
    e = xj - xi
    a1 = 0.5 * jnp.linalg.norm(jnp.cross(e, xk - xi), axis=-1)
    a2 = 0.5 * jnp.linalg.norm(jnp.cross(xl - xi, e), axis=-1)
    return jnp.sum(e * e, -1) / (a1 + a2)


def _unit(v):
    n2 = jnp.sum(v * v, -1, keepdims=True)
    ok = n2 > 0
    return jnp.where(ok, v / jnp.sqrt(jnp.where(ok, n2, 1.0)), 0.0)


#: A hinge folds freely up to this angle between its triangles' normals (degrees); past
#: it the fold barrier (`fold_barrier`) grows without bound as the fold nears 180 degrees
FOLD_BARRIER_DEG = 160.0
_C_HAT = float(np.cos(np.radians(FOLD_BARRIER_DEG)))


def fold_barrier(c):
    """b(c) = -(c - c_hat)^2 ln((1 + c) / (1 + c_hat)) for c = n1 . n2 < c_hat =
    cos(`FOLD_BARRIER_DEG`), else 0: zero with its first two derivatives at c_hat, +inf
    at c = -1 (the sheet folded flat onto itself), so no hinge folds through: the IPC
    barrier, on the fold of a hinge.  A real sheet of thickness H cannot fold sharper
    than a radius of about H / 2, and the hinge model has no thickness."""
    on = c < _C_HAT
    q = jnp.where(on, jnp.maximum(1.0 + c, 1e-300), 1.0 + _C_HAT) / (1.0 + _C_HAT)
    return jnp.where(on, -(c - _C_HAT) ** 2 * jnp.log(q), 0.0)


def bending_energy(x, hinge, weights, D, triangles, D_fold=None):
    """E_b (N mm) = sum_e w_e (D (1 - n1 . n2) + D_fold b(n1 . n2)) for positions x (N,
    3), b the `fold_barrier` (D_fold default D); the unit normals are computed once per
    triangle of ``triangles`` (M, 3) and read per hinge (columns 4, 5 of `hinges`)."""
    xt = x[triangles]
    n = _unit(jnp.cross(xt[:, 1] - xt[:, 0], xt[:, 2] - xt[:, 0]))
    c = jnp.sum(n[hinge[:, 4]] * n[hinge[:, 5]], -1)
    D_fold = D if D_fold is None else D_fold
    return jnp.sum(weights * (D * (1.0 - c) + D_fold * fold_barrier(c)))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Bending:
    """Bending stiffness as a multiple ``scale`` (traced, >= 0) of the physical plate
    modulus D of the membrane's material and thickness."""

    scale: Any = 1.0

    def validate(self):
        if _concrete(self.scale):
            s = np.asarray(self.scale, float)
            if not (np.all(np.isfinite(s)) and np.all(s >= 0)):
                raise ParameterError(f"bending scale must be finite and >= 0; got {self.scale}")
        return self
