"""Assembly of the membrane's nodal forces from its energies and the pressure load.

Pure JAX functions of the current positions ``x`` (N, 3) mm.  Elastic forces are
``-grad`` of the total strain energy (eq. 2.5); the pressure load is the follower force
F_i = P sum_T A_T n_T / 3 (sign set by the triangle orientation).  `prepare` computes the
reference geometry once per solve; it is differentiable with respect to ``params.ref``.
"""
from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp

from . import bending
from .materials import SpringGeometry
from ..geometry.mesh import local_reference, reference_areas, right_cauchy_green
from .problem import Params, Problem


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Reference:
    """Reference geometry: Dm_inv (M,2,2), area (M,) mm^2, node_area (N,) mm^2 (lumped),
    cot (M,3) cotangent of the reference angle at each vertex, springs: `SpringGeometry`
    or None."""

    Dm_inv: Any
    area: Any
    node_area: Any
    cot: Any
    springs: Any = None
    hinge_w: Any = None


def _scatter_nodes(values, triangles, n):
    """Sum per-triangle-vertex values (M, 3, ...) into nodes (N, ...)."""
    out = jnp.zeros((n,) + values.shape[2:], values.dtype)
    return out.at[triangles].add(values)


def prepare(problem: Problem, params: Params) -> Reference:
    """Reference geometry from ``params.ref``; differentiable."""
    tri = problem.triangles
    Dm = local_reference(params.ref, tri)
    area = reference_areas(Dm)
    Dm_inv = jnp.linalg.inv(Dm)
    n = problem.n_nodes
    node_area = _scatter_nodes(jnp.broadcast_to(area[:, None] / 3.0, tri.shape), tri, n)
    c1, c2 = Dm[..., 0], Dm[..., 1]
    pts = jnp.stack([jnp.zeros_like(c1), c1, c2], axis=1)  # (M,3,2) local vertices
    ea = jnp.roll(pts, -1, axis=1) - pts  # from vertex k to k+1
    eb = jnp.roll(pts, -2, axis=1) - pts  # from vertex k to k+2
    cot = jnp.sum(ea * eb, -1) / (2.0 * area[:, None])
    springs = None
    if params.material.needs_springs:
        # edge k is opposite vertex k: from vertex k+1 to k+2, in local coordinates
        c1, c2 = Dm[..., 0], Dm[..., 1]
        zero = jnp.zeros_like(c1)
        pts = jnp.stack([zero, c1, c2], axis=1)  # (M,3,2)
        e = jnp.roll(pts, -2, axis=1) - jnp.roll(pts, -1, axis=1)
        unit = e / jnp.linalg.norm(e, axis=-1, keepdims=True)
        ang = jnp.asarray(params.fibre_angle)
        if ang.ndim == 0:
            f = jnp.stack([jnp.cos(ang), jnp.sin(ang)])
            cos2 = jnp.einsum("mki,i->mk", unit, f) ** 2
        else:  # per spring (M, 3): the angle between spring and fibres
            cos2 = jnp.broadcast_to(jnp.cos(ang) ** 2, unit.shape[:2])
        springs = SpringGeometry(unit=unit, cos2=cos2)
    hinge_w = None
    if params.bending is not None and problem.hinges is not None:
        hinge_w = bending.hinge_weights(params.ref, problem.hinges)
    return Reference(Dm_inv=Dm_inv, area=area, node_area=node_area, cot=cot, springs=springs,
                     hinge_w=hinge_w)


def element_energies(x, problem: Problem, params: Params, ref: Reference):
    """Strain energy of each triangle (M,), N mm."""
    C = right_cauchy_green(x, problem.triangles, ref.Dm_inv)
    W = params.material.energy_density(C, ref.springs)
    return params.thickness * ref.area * W


def elastic_energy(x, problem, params, ref):
    """Total strain energy, N mm."""
    return jnp.sum(element_energies(x, problem, params, ref))


def stretch_admissible(x, problem, params, ref):
    """True when every triangle is within the model's stretch limit (Gent) and not collapsed.
    A minimum over the float margins, not an AND over booleans: the CI's machine has
    returned impossible Gent states from compiled solver loops (docs/known-limits.md)."""
    C = right_cauchy_green(x, problem.triangles, ref.Dm_inv)
    return jnp.min(params.material.stretch_margin(C)) > 0


def area_normals(x, triangles):
    """A_T n_T (M, 3) = (x1 - x0) x (x2 - x0) / 2."""
    xt = x[triangles]
    return 0.5 * jnp.cross(xt[:, 1] - xt[:, 0], xt[:, 2] - xt[:, 0])


def pressure_force(x, triangles, pressure):
    """Follower pressure load F_i = P sum_T A_T n_T / 3, (N, 3) N."""
    an = area_normals(x, triangles)
    return pressure / 3.0 * _scatter_nodes(jnp.broadcast_to(an[:, None, :], triangles.shape + (3,)),
                                           triangles, x.shape[0])


def internal_energy(x, problem, params, ref):
    """Strain energy plus bending (where the params have it), N mm."""
    e = elastic_energy(x, problem, params, ref)
    if ref.hinge_w is not None:
        D0 = bending.plate_modulus(params.material, params.thickness)
        e = e + bending.bending_energy(x, problem.hinges, ref.hinge_w,
                                       params.bending.scale * D0, problem.triangles, D0)
    return e


def membrane_force(x, problem, params, ref):
    """(-grad of the internal energy + the pressure load on free nodes (N, 3) N, zero rows
    at fixed nodes; ||pressure load|| on free nodes () N, the relative residual's scale)."""
    free = problem.free[:, None]
    g = jax.grad(internal_energy)(x, problem, params, ref)
    fp = pressure_force(x, problem.triangles, params.pressure) * free
    return (fp - g) * free, jnp.linalg.norm(fp)


def pressure_scale(x, problem, params):
    """||F_pressure|| over free nodes, the denominator of the relative residual."""
    f_p = pressure_force(x, problem.triangles, params.pressure) * problem.free[:, None]
    return jnp.linalg.norm(f_p)


def laplacian_apply(v, triangles, cot):
    """Cotangent Laplacian of the reference mesh applied to v (N, k): the stiffness of a
    membrane under unit isotropic tension (N/mm per unit tension)."""
    out = jnp.zeros_like(v)
    for k in range(3):  # edge opposite vertex k joins i = k+1 and j = k+2
        i, j = triangles[:, (k + 1) % 3], triangles[:, (k + 2) % 3]
        w = 0.5 * cot[:, k][:, None]
        d = w * (v[i] - v[j])
        out = out.at[i].add(d).at[j].add(-d)
    return out


# ------------------------------------------------------------- stiffness bounds
def _element_hessians(x, problem, params, ref, stiffest=False):
    """9x9 Hessian of each triangle's strain energy (M, 9, 9); with ``stiffest`` the
    material is taken at its largest tangent modulus (piecewise spring moduli)."""
    tri = problem.triangles
    mat = params.material.stiffest() if stiffest else params.material

    def e_one(xe, Dm_inv, area, springs):
        C = right_cauchy_green(xe.reshape(3, 3), jnp.array([[0, 1, 2]]), Dm_inv[None])
        sp = None if springs is None else jax.tree_util.tree_map(lambda a: a[None], springs)
        return params.thickness * area * mat.energy_density(C, sp)[0]

    xe = x[tri].reshape(-1, 9)
    return jax.vmap(jax.hessian(e_one))(xe, ref.Dm_inv, ref.area, ref.springs)


def block_diagonal(x, problem, params, ref):
    """3x3 diagonal blocks (N, 3, 3) of the elastic stiffness, for preconditioning."""
    Hs = _element_hessians(x, problem, params, ref).reshape(-1, 3, 3, 3, 3)
    diag = jnp.stack([Hs[:, k, :, k, :] for k in range(3)], axis=1)  # (M,3,3,3)
    return _scatter_nodes(diag, problem.triangles, problem.n_nodes)


def spectral_bound(H, squarings: int = 3):
    """Upper bound (B,) on the spectral radius max |lambda| of symmetric matrices H (B, n, n):
    rho(H)^(2m) <= tr(H^(2m)) = ||H^m||_F^2 with m = 2^squarings, so the bound exceeds
    rho by at most the factor n^(1/(2m)) (1.15 for n = 9, m = 8), and by far less when
    one eigenvalue dominates (StVK element stiffnesses of the closed benchmark valve:
    below 1.0001; `tests/test_energies.py`).  H is scaled by its Frobenius norm first (no
    overflow, in float32 too).  A few batched matrix products: ~5 ms against ~32 ms for
    `jnp.linalg.eigvalsh` on the 3987 9x9 element blocks of the benchmark valve.  Each
    product is written as n elementwise outer products (one fused loop): fed by the
    element Hessians of a FIRE mass refresh, XLA's batched ``B @ B`` cost 1.0 ms
    against 0.23 ms on the 1371 blocks at h = 1.5 mm."""
    f = jnp.sqrt(jnp.sum(H * H, axis=(-2, -1)))
    B = H / jnp.where(f > 0, f, 1.0)[..., None, None]
    for _ in range(squarings):
        B = sum(B[..., :, k, None] * B[..., None, k, :] for k in range(B.shape[-1]))
    t = jnp.sum(B * B, axis=(-2, -1))          # tr(B^(2m)) <= 1
    m2 = 2.0 ** (squarings + 1)
    return jnp.where(t > 0, f * jnp.where(t > 0, t, 1.0) ** (1.0 / m2), 0.0)


def stiffness_bound(x, problem, params, ref):
    """Per-node upper bound (N,) on the largest stiffness eigenvalue, N/mm.

    lambda_max(K) <= max_i sum_{T ni i} lambda_max(K_T) (the element matrices are assembled
    into K), with the material at its stiffest tangent modulus and lambda_max(K_T) bounded
    by `spectral_bound`.  Adds the pressure stiffness (|P| times the edge lengths at the
    node) and the bending hinges'; contact stiffness is the solver's (`solvers.fire`)."""
    tri = problem.triangles
    Hs = _element_hessians(x, problem, params, ref, stiffest=True)
    lam = spectral_bound(Hs)  # (M,)
    xt = x[tri]
    emax = jnp.max(jnp.linalg.norm(xt - jnp.roll(xt, 1, axis=1), axis=-1), axis=-1)
    per_tri = lam + jnp.abs(params.pressure) * emax / 3.0
    bound = _scatter_nodes(jnp.broadcast_to(per_tri[:, None], tri.shape), tri, problem.n_nodes)
    if ref.hinge_w is not None:
        # hinge stiffness ~ D w_e / (altitude)^2 on each of its four nodes
        D = params.bending.scale * bending.plate_modulus(params.material.stiffest(),
                                                         params.thickness)
        alt2 = (2.0 * ref.area / emax) ** 2
        per = 4.0 * D * ref.hinge_w / jnp.min(alt2)
        hv = jnp.broadcast_to(per[:, None], problem.hinges[:, :4].shape)
        bound = bound + jnp.zeros(problem.n_nodes, bound.dtype).at[problem.hinges[:, :4]].add(hv)
    return bound
