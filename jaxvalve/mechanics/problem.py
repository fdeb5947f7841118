"""A membrane problem: topology (static) and physical parameters (traced).

`Problem` holds integer/boolean arrays only: triangles, the fixed-node mask and the body id
per node.  `Params` holds every float that a gradient may be taken with respect to:
reference coordinates, the material, thickness H (mm), pressure P (MPa), fibre angle and
contact law.  Both are pytrees, so a jitted solve compiled once serves every value of
E, nu, mu, Jm, H or P.
"""
from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import MeshError, ParameterError
from .materials import Material, _check_positive, _concrete
from ..geometry.mesh import validate_mesh

MMHG = 1.33322e-4  # MPa per mmHg


def mmhg(p):
    """Pressure in MPa from mmHg."""
    return p * MMHG


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Problem:
    """Mesh topology and boundary conditions.

    triangles (M, 3) int32, oriented: pressure acts along +n, n ~ (x1-x0) x (x2-x0).
    fixed (N,) bool: nodes held at their initial position (sutured edge, clamp).
    body (N,) int32: body id per node (leaflet index); contact acts between bodies.
    hinges (K, 6) int32: interior edges (i, j, k, l, t1, t2) for the bending energy
    (`jaxvalve.mechanics.bending.hinges`), or None.
    """

    triangles: Any
    fixed: Any
    body: Any
    hinges: Any = None

    @property
    def n_nodes(self):
        return self.fixed.shape[0]

    @property
    def free(self):
        return ~self.fixed


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Params:
    """Traced parameters.

    ref (N, 2|3) mm: stress-free reference coordinates.
    material: a `jaxvalve.mechanics.materials` model.
    thickness: H, mm.  pressure: P, MPa (use `mmhg`).
    fibre_angle: radians, fibre direction in the 2D template frame (scalar), or per
        triangle edge (M, 3); used by anisotropic spring models only.
    contact: None, `SmoothContact` or `PaperContact`.
    bending: None (a pure membrane, as specified) or `jaxvalve.mechanics.bending.Bending`.
    """

    ref: Any
    material: Material
    thickness: Any = 0.3
    pressure: Any = 0.0
    fibre_angle: Any = 0.0
    contact: Any = None
    bending: Any = None

    def replace(self, **kw):
        return dataclasses.replace(self, **kw)


def make_problem(ref, triangles, fixed=None, body=None):
    """Validate a mesh and boundary data; return ``(Problem, ref)`` as JAX arrays.

    fixed: bool (N,) or integer indices of fixed nodes.  body: int (N,), default all 0.
    """
    ref, tri = validate_mesh(ref, triangles)
    n = ref.shape[0]
    used = np.zeros(n, bool)
    used[tri.ravel()] = True
    if not used.all():
        raise MeshError(f"node {int(np.argmin(used))} belongs to no triangle; remove unused nodes")
    if fixed is None:
        fixed_mask = np.zeros(n, bool)
    else:
        fixed = np.asarray(fixed)
        if fixed.dtype == bool:
            if fixed.shape != (n,):
                raise MeshError(f"fixed mask must have shape ({n},); got {fixed.shape}")
            fixed_mask = fixed
        else:
            if fixed.size and (fixed.min() < 0 or fixed.max() >= n):
                raise MeshError(f"fixed node indices must lie in [0, {n - 1}]")
            fixed_mask = np.zeros(n, bool)
            fixed_mask[fixed] = True
    if fixed_mask.all():
        raise MeshError("every node is fixed; at least one node must be free")
    body = np.zeros(n, np.int32) if body is None else np.asarray(body, np.int32)
    if body.shape != (n,):
        raise MeshError(f"body must have shape ({n},); got {body.shape}")
    if np.any(body[tri[:, 0]] != body[tri[:, 1]]) or np.any(body[tri[:, 0]] != body[tri[:, 2]]):
        raise MeshError("a triangle joins nodes of different bodies; body ids must be constant "
                        "on each triangle")
    from .bending import hinges
    prob = Problem(jnp.asarray(tri), jnp.asarray(fixed_mask), jnp.asarray(body),
                   jnp.asarray(hinges(tri)))
    return prob, jnp.asarray(ref)


def validate_params(params: Params):
    """Raise `ParameterError` for non-positive thickness, non-finite values or bad moduli.
    Values that are tracers (inside jit/grad) are skipped; checks run at the API boundary."""
    if _concrete(params.thickness):
        _check_positive("thickness H", params.thickness, "params")
    if _concrete(params.pressure):
        p = np.asarray(params.pressure, float)
        if not np.all(np.isfinite(p)):
            raise ParameterError(f"pressure P must be finite (MPa); got {params.pressure}")
    if _concrete(params.ref) and not np.all(np.isfinite(np.asarray(params.ref))):
        raise ParameterError("ref holds a non-finite coordinate; every coordinate must be finite")
    if _concrete(params.fibre_angle) and not np.all(np.isfinite(np.asarray(params.fibre_angle))):
        raise ParameterError("fibre_angle must be finite (radians)")
    params.material.validate()
    if params.contact is not None and hasattr(params.contact, "validate"):
        params.contact.validate()
    if params.bending is not None:
        params.bending.validate()
    return params
