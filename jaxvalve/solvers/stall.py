"""Why a solve stopped short of equilibrium: is the force continuous where it stopped?

A solver that hits its step cap far above its tolerance is either slow (stiff, soft or
nearly free modes) or sitting on a jump of the force, where no point has zero force and
no solver can bring the residual below the jump.  `probe` tells them apart with two force
evaluations: every free node moves along the residual force by ``step`` times its share
(the node with the largest force moves ``step`` mm), and the change of each force term
is compared with what a continuous force allows at that move.  At step = 1e-7 mm a
stiffness of 1e3 N/mm changes a force by 1e-4 N; a change far above both that and the
residual itself is a jump.  On the soft valves of the paper's Table 4 the one-sided
contact force jumps by 0.27-0.44 N where a free edge has folded round another leaflet's
(`benchmarks/stall_probe.py`, docs/known-limits.md).

A third evaluation, at a random move of every free coordinate within half its spacing in
the solve's precision, measures a third cause: the residual is at the precision's
rounding floor.  In float32 the positions' own spacing sets it: at h = 2 mm and 3 mmHg
the float64 residual force at a float64 equilibrium rounded to float32 is 2e-4 (E = 0.1
MPa) to 6e-3 (E = 20 MPa) of the pressure force, above the default rtol of 1e-4, while
the force terms' arithmetic rounding alone is 3e-7 to 4e-6 (`StallReport.floor`).

The barrier law without self-contact (`BarrierTopology.self_contact` False) is solved by
projected Newton with a line search that keeps every edge's fold below
`checks.FOLD_DEG`.  Its solves stop short at that bound when a crease wants to fold
further (`fold_bound_cause`): the hinge energy D w (1 - cos theta) resists a fold with a
moment D w sin(theta), which falls past 90 degrees (soft StVK, E = 0.05 MPa, h = 2 mm:
every stagnated barrier solve of the stress run ended with one edge at 150.00 degrees;
docs/known-limits.md).
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from ..contact.neighbours import whole_lists
from ..quick_jit import quick_jit
from ..mechanics import assembly
from . import equilibrium
from ..valve.checks import FOLD_DEG, fold_angles

__all__ = ["StallReport", "probe", "stopped_cause", "fold_bound_cause", "TERMS"]

#: The force terms probed: strain, bending, contact (`assembly.force_parts`).
TERMS = ("elastic", "bending", "contact")
#: Largest stiffness (N/mm) a continuous force is granted; beyond it a change is a jump.
STIFFNESS_CAP = 1e3
#: a residual force within this multiple of its rounding floor is at the floor: a solve
#: there wanders over grid points whose residuals are about 1-2 times ``floor_state``
#: (the float32 stress runs at E >= 1 MPa, h = 2 mm, stopped at 1.0-1.6 times it)
AT_FLOOR = 3.0
#: an edge folded to within this (degrees) of `checks.FOLD_DEG` is at the barrier Newton's
#: fold bound (its line search halves steps against the bound 30 times, so the solve
#: stops within ~1e-9 degrees of it)
AT_FOLD_BOUND_DEG = 0.01


@dataclasses.dataclass(frozen=True)
class StallReport:
    """force (N): the residual force's norm over the free nodes; jumps: per term of
    `TERMS`, the norm (N) of its change under the probe move; node: where the largest
    change of the term that jumped most lies; step: the move of the largest node (mm);
    floor (N): the rounding floor of the residual force in the solve's precision, the sum
    of ``floor_arithmetic``, its machine epsilon times the norm of the nodes' summed term
    magnitudes (the terms cancel to the residual, so it cannot be computed more exactly
    than that), and ``floor_state``, the change of the residual force when every free
    coordinate moves by a random fraction (uniform in +-1/2) of its spacing in that
    precision (the point of that grid nearest an exact equilibrium lies about that far
    from it, so no solve in that precision gets closer; in float32 this part dominates:
    coordinates of ~16 mm are 1.9e-6 mm apart); precision: that precision's name."""

    force: float
    jumps: dict
    node: int
    step: float
    floor_arithmetic: float = 0.0
    floor_state: float = 0.0
    precision: str = "float64"

    @property
    def floor(self) -> float:
        """The rounding floor (N): ``floor_arithmetic`` + ``floor_state``."""
        return self.floor_arithmetic + self.floor_state

    @property
    def at_floor(self) -> bool:
        """True where the residual force is within `AT_FLOOR` times its rounding floor."""
        return bool(self.force <= AT_FLOOR * self.floor)

    @property
    def term(self) -> str:
        return max(self.jumps, key=self.jumps.get)

    @property
    def jumped(self) -> bool:
        """True where the largest change exceeds both the residual force / 10 and what a
        stiffness of `STIFFNESS_CAP` allows at the move."""
        j = self.jumps[self.term]
        return bool(j > 0.1 * self.force and j > STIFFNESS_CAP * self.step)

    def cause(self) -> str:
        """One line for reports."""
        j = self.jumps[self.term]
        if self.jumped:
            return (f"the {self.term} force is discontinuous at node {self.node}: a "
                    f"{self.step:g} mm move changes it by {j:.2g} N against a residual "
                    f"force of {self.force:.2g} N, so no solver can converge here")
        if self.at_floor:
            return (f"the residual force {self.force:.2g} N is at the rounding floor of "
                    f"{self.precision} (about {self.floor:.2g} N: {self.floor_state:.2g} N "
                    "from the spacing of its positions, "
                    f"{self.floor_arithmetic:.2g} N from the force terms cancelling), so "
                    "the tolerance is below what this precision can resolve")
        return (f"the force is continuous here (largest change {j:.2g} N, {self.term}, for "
                f"a {self.step:g} mm move): the solve is slow, not stuck on a jump (its "
                f"residual force {self.force:.2g} N, the rounding floor of {self.precision} "
                f"about {self.floor:.2g} N)")

    def as_dict(self):
        return dict(force=self.force, jumps=dict(self.jumps), node=self.node,
                    step=self.step, jumped=self.jumped, floor=self.floor,
                    floor_arithmetic=self.floor_arithmetic, floor_state=self.floor_state,
                    precision=self.precision, cause=self.cause())


@quick_jit
def _terms(x, problem, params, nbrs):
    """Elastic, bending, contact and pressure forces (4, N, 3), fixed rows zero.  Run
    twice per probe, so compiled for compile time: the contact on its whole pair lists
    (`contact.neighbours.whole_lists`), with `quick_jit`'s CPU emitters."""
    ref = assembly.prepare(problem, params)
    el = -jax.grad(assembly.elastic_energy)(x, problem, params, ref)
    with whole_lists():
        cons, fp, fpc = assembly.force_parts(x, problem, params, ref, nbrs)
    bare = params.replace(contact=None)
    no_contact = -jax.grad(assembly.conservative_energy)(x, problem, bare, ref)
    free = problem.free[:, None]
    return jnp.stack([el, no_contact - el, cons - no_contact + fpc, fp]) * free


def probe(problem, params, x, *, skin=equilibrium.DEFAULT_SKIN, step=1e-7,
          precision="float64", seed=0) -> StallReport:
    """Probe the force at positions x (N, 3) mm of ``problem`` under ``params``, each
    evaluation with contact pair lists built at its own positions (host side; evaluate
    in float64).  precision: that of the solve being judged (its rounding floor); seed:
    that of the random move that measures the floor's state part (a third evaluation,
    skipped where the move rounds back to x, as it does in float64)."""
    def at(y):
        nbrs = None
        if params.contact is not None:
            nbrs = equilibrium.init_pairs(params.contact, problem, y, skin)
        return np.asarray(_terms(y, problem, params, nbrs))

    x = jnp.asarray(x)
    f0 = at(x)
    F = f0.sum(0)
    big = float(np.max(np.linalg.norm(F, axis=1)))
    u = F / big if big > 0 else F
    f1 = at(x + step * jnp.asarray(u, x.dtype))
    change = np.linalg.norm(f1[:3] - f0[:3], axis=2)            # (3, N)
    jumps = {t: float(np.linalg.norm(change[k])) for k, t in enumerate(TERMS)}
    k = TERMS.index(max(jumps, key=jumps.get))
    dtype = np.dtype(precision)
    arithmetic = float(np.finfo(dtype).eps) * float(np.linalg.norm(np.abs(f0).sum(0)))
    x64 = np.asarray(x, np.float64)
    spacing = np.spacing(np.abs(x64).astype(dtype)).astype(np.float64)
    free = np.asarray(problem.free, bool)[:, None]
    move = np.random.default_rng(seed).uniform(-0.5, 0.5, x64.shape) * spacing * free
    moved = x64 + move            # in float64 a move within half a spacing rounds back
    state = 0.0 if np.array_equal(moved, x64) else float(
        np.linalg.norm(at(jnp.asarray(moved, x.dtype)).sum(0) - F))
    return StallReport(force=float(np.linalg.norm(F)), jumps=jumps,
                       node=int(np.argmax(change[k])), step=float(step),
                       floor_arithmetic=arithmetic, floor_state=state, precision=dtype.name)


def fold_bound_cause(problem, x):
    """A line naming the edge of state x (N, 3) mm folded to `checks.FOLD_DEG` (within
    `AT_FOLD_BOUND_DEG`), the bound of the barrier Newton's line search, or None where no
    edge is that far folded."""
    x = np.asarray(x, np.float64)
    if not np.all(np.isfinite(x)):
        return None
    tri = np.asarray(problem.triangles)
    pairs, angle, good = fold_angles(tri, x)
    angle = np.where(good, angle, 0.0)
    if not len(pairs) or angle.max() < FOLD_DEG - AT_FOLD_BOUND_DEG:
        return None
    k = int(np.argmax(angle))
    i, j = sorted(set(tri[pairs[k, 0]].tolist()) & set(tri[pairs[k, 1]].tolist()))
    return (f"the edge between nodes {i} and {j} is folded to {angle[k]:.2f} degrees, the "
            f"{FOLD_DEG:g}-degree bound of the barrier Newton's line search, which admits "
            "no step that folds it further (a crease at the mesh size, which the hinge "
            "bending resists less the more it is folded past 90 degrees)")


def stopped_cause(problem, params, result: str, x, *, skin, precision="float64",
                  fold_bound=True):
    """`probe`'s verdict (a line) on a solve of ``problem`` under ``params`` that stopped
    short of equilibrium at its step cap or stagnated (``result`` 'max_steps_reached' or
    'stagnation') in state x (N, 3) mm, evaluated in float64; on the barrier law (solved
    by its own Newton), `fold_bound_cause` where its line search bounds folds
    (``fold_bound``: the barrier without self-contact, `BarrierTopology.self_contact`).
    None for any other result, for non-finite x, for the paper's law (no pointwise
    ``energy``) and for a barrier solve that stopped away from the fold bound or had none
    (with self-contact an edge may fold past 150 degrees: the soft StVK valve of template
    (c) at 0.1 MPa stopped at 200 mmHg with one at 175 degrees)."""
    contact = params.contact
    if result not in ("max_steps_reached", "stagnation"):
        return None
    if not np.all(np.isfinite(np.asarray(x))):
        return None
    if getattr(contact, "barrier", False):
        return fold_bound_cause(problem, x) if fold_bound else None
    if not (contact is None or hasattr(contact, "energy")):
        return None
    p64 = jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float64), params)
    return probe(problem, p64, jnp.asarray(np.asarray(x, np.float64)), skin=skin,
                 precision=precision).cause()
