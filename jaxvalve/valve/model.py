"""A three-leaflet valve in an aortic root: assembly, placement and closure.

`build_valve(root, mesh)` stacks three copies of one leaflet mesh into a single membrane
problem (body id = leaflet index), fixes the sutured-edge nodes on the suturing paths and
returns a `Valve`.  `settle(valve, ...)` is the closure at P = 0 that gives the start;
`close(valve, ...)` closes it under a pressure.
"""
from __future__ import annotations

import dataclasses
import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..solvers import equilibrium
from ..contact import BarrierContact
from ..errors import ConvergenceError, ParameterError
from ..geometry.leaflet_mesh import LeafletMesh
from .placement import place_leaflet
from ..mechanics.problem import Params, Problem, make_problem, mmhg
from ..solvers import FIRE, RESULTS, Solution

__all__ = ["Valve", "build_valve", "settle", "close", "state_failure", "leaflet_crossings"]


#: The valve's own outcomes (`state_failure`): the solver met its tolerance, but the state
#: is not a valid closed valve.  Names and messages, apart from the solver's `RESULTS`.
STATE_FAILURES = {
    "leaflets_cross": ("the force residual met the tolerance but leaflets cross one another "
                       "or themselves (exact triangle-triangle test)"),
    "inverted_triangles": ("the force residual met the tolerance but a triangle is folded "
                           "over its neighbour or collapsed "
                           "(jaxvalve.valve.checks.triangle_checks)"),
    "nonfinite": RESULTS.nonfinite.message,
}


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ValveSolution(Solution):
    """A `Solution` with the valve's state check (`close(..., check_state=True)`).

    state: None when the state passed (or was not checked), else a key of
    `STATE_FAILURES`.  ``result`` stays the solver's own code; ``converged`` is False and
    ``status`` names the failed check when ``state`` is set."""

    state: str | None = dataclasses.field(default=None, metadata=dict(static=True))

    @property
    def converged(self):
        return self.state is None and super().converged

    @property
    def status(self) -> str:
        return self.state if self.state is not None else super().status

    def _message(self) -> str:
        return STATE_FAILURES[self.state] if self.state is not None else super()._message()


@dataclasses.dataclass(frozen=True)
class Valve:
    """Three leaflets in a root.

    problem: the stacked membrane problem (fixed = sutured nodes, body = leaflet 0..2).
    ref (N, 2) mm: each node's template coordinates (the stress-free state).
    x_placed (N, 3) mm: mapped to the commissure planes, sutured nodes on the paths.
    x_start (N, 3) mm: after the closure at P = 0 (equal to x_placed until `settle`).
    free_edge (N,) bool; suture_strain (3,): path length / sutured length - 1.
    """

    root: Any
    leaflet: LeafletMesh
    problem: Problem
    ref: Any
    x_placed: np.ndarray
    x_start: np.ndarray
    free_edge: np.ndarray
    suture_strain: np.ndarray

    @property
    def n_leaflets(self):
        return 3

    @property
    def nodes_per_leaflet(self):
        return self.leaflet.n_nodes

    @property
    def triangles(self):
        return np.asarray(self.problem.triangles)

    @property
    def body(self):
        return np.asarray(self.problem.body)

    @functools.cached_property
    def contact_topology(self):
        """`jaxvalve.contact.pairs.ContactTopology` of the three leaflets: edges, leaflet
        ids, and the commissure pins where neighbours are sewn to one point."""
        from ..contact.pairs import contact_topology
        return contact_topology(self.triangles, self.body, np.asarray(self.problem.fixed),
                                self.x_placed)

    def leaflet_slice(self, i):
        n = self.nodes_per_leaflet
        return slice(i * n, (i + 1) * n)

    def params(self, material, pressure_mmhg=80.0, contact=None, thickness=0.3,
               fibre_angle=0.0, bending=None):
        """`Params` for this valve (pressure in mmHg)."""
        return Params(ref=self.ref, material=material, thickness=thickness,
                      pressure=mmhg(pressure_mmhg), fibre_angle=fibre_angle,
                      contact=BarrierContact() if contact is None else contact,
                      bending=bending)


def build_valve(root, lmesh: LeafletMesh) -> Valve:
    """Stack three copies of ``lmesh`` and place them in ``root``."""
    n = lmesh.n_nodes
    centre = np.asarray(root.origin, float)
    xs, strain = [], []
    for i in range(3):
        c0, c1 = root.commissures[i], root.commissures[(i + 1) % 3]
        xs.append(place_leaflet(lmesh, c0, c1, root.paths[i], root.axis, centre))
        strain.append(root.path_lengths[i] / lmesh.template.sutured_length - 1.0)
    strain = np.asarray(strain)
    if np.any(np.abs(strain) > 0.25):
        raise ParameterError(
            f"suturing paths are {np.round(100 * strain, 1)} % longer than the template's "
            f"sutured edge ({lmesh.template.sutured_length:.2f} mm); the placement allows "
            "at most 25 %: choose a template whose sutured edge fits the root")
    x = np.concatenate(xs)
    tri = np.concatenate([lmesh.triangles + i * n for i in range(3)])
    fixed = np.tile(lmesh.sutured_mask, 3)
    body = np.repeat(np.arange(3), n)
    ref = np.tile(lmesh.points, (3, 1))
    prob, ref = make_problem(ref, tri, fixed=fixed, body=body)
    return Valve(root, lmesh, prob, ref, x, x, np.tile(lmesh.free_mask, 3), strain)


def settle(valve: Valve, material, *, solver=None, thickness=0.3) -> Valve:
    """The closure at P = 0 from the placement: a short relaxation of the harmonic surface
    (the paper's Algorithm 2.1 at P = 0 with its own stop rule plays the same part).  An
    unloaded membrane has slack, zero-stiffness directions, so it is not driven to a tight
    residual: the default stops at a relative residual of 1e-3 or after 2000 FIRE steps,
    whichever comes first.  Unloaded leaflets hang apart, so no contact is computed here.
    Returns the valve with ``x_start`` set and the relaxation's `Solution`."""
    solver = FIRE(rtol=1e-3, max_steps=2000, patience=0) if solver is None else solver
    params = valve.params(material, 0.0, None, thickness).replace(contact=None)
    sol = equilibrium.solve(valve.problem, params, jnp.asarray(valve.x_placed), solver,
                            throw=False)
    if not np.all(np.isfinite(np.asarray(sol.x))):
        raise ConvergenceError("the closure at P = 0 produced non-finite positions", sol)
    return dataclasses.replace(valve, x_start=np.asarray(sol.x)), sol


def close(valve: Valve, material, pressure_mmhg=80.0, *, solver=None, contact=None,
          thickness=0.3, fibre_angle=0.0, bending=None, x0=None, throw=True,
          check_state=False, caps=None, ref=None):
    """One equilibrium solve of the valve under ``pressure_mmhg`` from ``x0`` (default
    x_start), by ``solver`` (default the engine).  Closing a valve under its loads, with
    continuation in pressure, is `jaxvalve.valve.closure` (the one closure driver), which
    calls this for every solve.

    check_state: test a converged state with `state_failure` (host side): leaflets that
    cross, or a triangle collapsed, make the returned `ValveSolution` not converged
    (raised as `ConvergenceError` when ``throw``).  caps: pair-list capacities to start
    from (`jaxvalve.contact.pairs.Capacities`).  ref (N, 2|3) mm: the leaflets' reference
    where it is not ``valve.ref`` (a mapped template, `optimize.Evaluator`; traced, so a
    new template does not recompile)."""
    params = valve.params(material, pressure_mmhg, contact, thickness, fibre_angle, bending)
    if ref is not None:
        params = params.replace(ref=ref)
    x0 = valve.x_start if x0 is None else x0
    sol = equilibrium.solve(valve.problem, params, jnp.asarray(x0), solver,
                            throw=throw and not check_state, topo=valve.contact_topology,
                            caps=caps)
    barrier = isinstance(params.contact, BarrierContact)
    sol = (checked(valve, sol, ref=ref, self_contact=barrier) if check_state
           else ValveSolution(**_fields(sol)))
    if throw and check_state and not sol.converged:
        raise ConvergenceError(f"valve closure at {pressure_mmhg:g} mmHg did not converge: "
                               f"{sol.describe()}", sol)
    return sol


def _fields(sol: Solution) -> dict:
    return {f.name: getattr(sol, f.name) for f in dataclasses.fields(Solution)}


def checked(valve: Valve, sol: Solution, ref=None, self_contact: bool = False
            ) -> ValveSolution:
    """``sol`` as a `ValveSolution` carrying the state check (`state_failure`) of a state
    the solver accepted.  ref: the leaflets' reference (N, 2|3) mm where it is not
    ``valve.ref`` (a mapped template, `optimize.Evaluator`); self_contact: the state
    comes from a law with self-contact (`state_failure`).  The one check that `close`,
    `simulate`, `simulate_batch`, the stress suite and the optimiser apply."""
    state = None
    if sol.converged:
        v = valve if ref is None else dataclasses.replace(valve, ref=np.asarray(ref))
        state = state_failure(v, sol.x, self_contact=self_contact)
    return ValveSolution(**_fields(sol), state=state)


def state_failure(valve: Valve, x, *, self_contact: bool = False):
    """Why the state x (N, 3) mm, which a solver calls converged, is still not a valid
    closed valve, as a key of `STATE_FAILURES`: "leaflets_cross" (an exact triangle-triangle
    test finds leaflets crossing), "inverted_triangles" (a triangle collapsed or turned
    over, `jaxvalve.valve.checks`), "nonfinite", or None when it passes.

    The exact test also looks for triangles of one leaflet that share no node and
    intersect (`intersect.self_intersections`), whatever the law: the penalty law keeps
    leaflets apart but not a leaflet off itself, and a FIRE closure of template (c) of the
    stress suite (neo-Hookean, 1 MPa, 3 mmHg) converged to a leaflet folded through
    itself with no edge past the fold bound, which only ipctk had found.
    self_contact: x comes from a law that keeps each leaflet off itself (the barrier's
    self-contact, CCD on every step).  A sharp crease (two triangles' normals more than
    `checks.FOLD_DEG` apart) is then a fold held open, not a triangle turned over, and
    is not a failure."""
    from .checks import FOLD_DEG, triangle_checks
    from .intersect import self_intersections
    x = np.asarray(x, np.float64)
    if not np.all(np.isfinite(x)):
        return "nonfinite"
    if len(leaflet_crossings(valve, x)):
        return "leaflets_cross"
    if len(self_intersections(x, valve.triangles, valve.body)):
        return "leaflets_cross"
    rep = triangle_checks(valve.ref, valve.triangles, x,
                          fold_deg=180.0 if self_contact else FOLD_DEG)
    if not rep.ok:
        return "inverted_triangles"
    return None


def commissure_groups(valve: Valve, x) -> np.ndarray:
    """(N,) for each node of the state x (N, 3) mm, the commissure group it is sewn into,
    or -1: fixed nodes of different leaflets at the same point (to 1e-9 of the root's size)
    are the leaflets' shared corners.  Read from x itself, not from the root's commissure
    points, because a design map (`optimize.Evaluator`) moves the corners with the
    template: 1.6 mm per mm of r on the benchmark root."""
    x = np.asarray(x, float)
    fixed = np.flatnonzero(np.asarray(valve.problem.fixed))
    p, b = x[fixed], np.asarray(valve.body)[fixed]
    tol = 1e-9 * max(1.0, float(np.max(np.abs(p))))
    same = np.linalg.norm(p[:, None] - p[None], axis=-1) <= tol        # (F, F)
    shared = np.any(same & (b[:, None] != b[None]), axis=1)
    # the group of a shared node: its point's first fixed node, numbered from 0
    group = np.full(x.shape[0], -1)
    group[fixed[shared]] = np.unique(np.argmax(same, axis=1)[shared], return_inverse=True)[1]
    return group


def leaflet_crossings(valve: Valve, x) -> np.ndarray:
    """Pairs (P, 2) of triangles of different leaflets that intersect in ``x`` (N, 3),
    by an exact triangle-triangle test that shares no code with the contact law.

    Neighbouring leaflets are sewn to the same commissure point, so triangles that hold a
    node at one commissure touch there by construction: a pair in which both triangles
    hold a node of the same commissure group (`commissure_groups`) is not counted."""
    from .intersect import leaflets_intersect

    x = np.asarray(x, float)
    tri = valve.triangles
    pairs = leaflets_intersect(x, tri, valve.body)
    if len(pairs) == 0:
        return pairs
    g = commissure_groups(valve, x)[tri]                                  # (M, 3)
    n = int(g.max()) + 1
    if n == 0:
        return pairs
    at = np.any(g[:, :, None] == np.arange(n)[None, None], axis=1)      # (M, groups)
    shared = np.any(at[pairs[:, 0]] & at[pairs[:, 1]], axis=1)
    return pairs[~shared]
