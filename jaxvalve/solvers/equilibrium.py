"""The equilibrium solve: one entry for every membrane, with or without contact.

``solve(problem, params, x0, solver)`` finds x with residual(x) = 0 on the free nodes,
starting from x0 (N, 3) mm; fixed nodes stay at x0.

* Membranes without contact: `NewtonKrylov` (default), `FIRE` or `FixedPoint`.
* Barrier contact (`jaxvalve.contact.BarrierContact`, the valve's law): the `Engine`,
  FIRE in one compiled loop on the in-jit pair lists (`jaxvalve.contact.pairs`), then,
  where FIRE stagnates above the tolerance, Newton on the exact tangent from FIRE's best
  state (`jaxvalve.solvers.finish`).
* The paper's law (`PaperContact`): `FixedPoint`, the paper's Algorithm 2.1.

A solve called with concrete values runs its loop from the host in stretches of whole
multiples of `progress.BEACON_EVERY` steps and reports its progress after each
(`jaxvalve.progress.beacon`); inside a trace (jit, vmap) the loop is one program.  Pair lists that overflow their capacities are
grown and the solve is run again.  Reverse-mode derivatives of a converged state come from
the implicit function theorem (`implicit_state`, `jaxvalve.solvers.adjoint`), never from
unrolling the solver.
"""
from __future__ import annotations

import dataclasses
import functools
import time

import jax
import jax.numpy as jnp
import numpy as np

from .. import progress
from ..contact import pairs as pair_lists
from ..contact.barrier import BarrierContact, collision_weights, forces as barrier_forces
from ..contact.paper import PaperContact, vicinity_threshold
from ..errors import ConvergenceError, ParameterError
from ..mechanics import assembly
from ..mechanics.problem import Params, Problem, validate_params
from . import adjoint
from .base import (RESULTS, EquilibriumSystem, Solution, Stats, check_settings, end,
                   escape_distance,
                   relative_residual, run, running, start)
from .fire import FIRE
from .fixed_point import FixedPoint
from .newton import NewtonKrylov

__all__ = ["Engine", "solve", "finish", "fire_batch", "make_system", "Contact", "SKIN",
           "MARGIN"]

#: the pair lists' candidate skin and active margin (mm, `jaxvalve.contact.pairs`): the
#: candidates are rebuilt about every (SKIN - MARGIN) / 2 of node travel, the active
#: pairs re-selected every MARGIN / 2
SKIN = 1.0
MARGIN = 0.2


@dataclasses.dataclass(frozen=True)
class Engine:
    """The closure engine's settings: FIRE to a relative residual ``rtol`` (at most
    ``max_steps`` steps, stagnation after ``patience`` steps without halving its
    residual), then, where FIRE stagnated or reached its cap with a best residual below
    ``finish_below`` (near an equilibrium, where Newton converges), Newton on the exact
    tangent from its best state (`jaxvalve.solvers.finish`, at most ``newton_steps``
    steps)."""

    rtol: float = 1e-4
    max_steps: int = 20_000
    patience: int = 300
    dt_max: float = 1.5
    newton_steps: int = 40
    finish_below: float = 0.05
    #: failures after which continuation in pressure cuts the load step
    #: (`jaxvalve.solvers.continuation.cut_on`): a finish that stalled, or a state with a
    #: collapsed triangle, may pass from a nearer equilibrium
    cut_on = ("stagnation", "max_steps_reached", "inverted_triangles")

    def __post_init__(self):
        check_settings(self, dict(rtol="positive", max_steps="count", patience="count",
                                  dt_max="positive", newton_steps="count",
                                  finish_below="positive"))

    def fire(self) -> FIRE:
        return FIRE(rtol=self.rtol, max_steps=self.max_steps, patience=self.patience,
                    dt_max=self.dt_max)


@dataclasses.dataclass(frozen=True)
class Contact:
    """What the solve's system knows of the contact law: ``kind`` ("barrier", "paper" or
    None) and, for the pair lists, their static capacities."""

    kind: str | None = None
    caps: pair_lists.Capacities | None = None


def _kind(params: Params):
    c = params.contact
    if c is None:
        return None
    if isinstance(c, BarrierContact):
        return "barrier"
    if isinstance(c, PaperContact):
        return "paper"
    raise ParameterError(f"params.contact must be None, BarrierContact or PaperContact; got "
                         f"{type(c).__name__}")


def make_system(problem: Problem, contact: Contact) -> EquilibriumSystem:
    """The functions a solver needs, with ``args`` = dict(params, ref, f0, x_start,
    escape) and, with contact, the pair ``lists``, their ``topo`` and, for the barrier,
    the collision ``weights`` (for the paper's law its step ``delta``)."""
    free = problem.free

    def parts(y, a):
        p = a["params"]
        F, s = assembly.membrane_force(y, problem, p, a["ref"])
        dmin = jnp.full(y.shape[:1], jnp.inf, y.dtype)
        stiff = jnp.zeros(y.shape[:1], y.dtype)
        if contact.kind == "barrier":
            _, g, dmin, stiff = barrier_forces(p.contact, y, a["lists"].act, a["weights"])
            F = F - g * free[:, None]
        elif contact.kind == "paper":
            F = F + p.contact.force(y, F, a["delta"], a["lists"].act, a["topo"].node_body,
                                    problem.triangles) * free[:, None]
        return F, jnp.where(p.pressure != 0, s, a["f0"]), dmin, stiff

    def force(y, a):
        return parts(y, a)[0]

    def scale(y, a):
        p = a["params"]
        return jnp.where(p.pressure != 0, assembly.pressure_scale(y, problem, p), a["f0"])

    def admissible(y, a):
        return assembly.stretch_admissible(y, problem, a["params"], a["ref"])

    def bound(y, a):
        return assembly.stiffness_bound(y, problem, a["params"], a["ref"])

    def block_diag(y, a):
        return assembly.block_diagonal(y, problem, a["params"], a["ref"])

    def update(y, a):
        if contact.kind is None:
            return a
        return dict(a, lists=pair_lists.update(a["lists"], a["topo"], a["params"].ref, y,
                                               contact.caps))

    def overflow(a):
        if contact.kind is None:
            return jnp.asarray(False)
        return pair_lists.overflow_flag(a["lists"], contact.caps)

    def step_cap(y, a):
        if contact.kind is None:
            return jnp.asarray(jnp.inf, y.dtype)
        return a["lists"].step_cap(y)

    def laplacian(v, a):
        return assembly.laplacian_apply(v, problem.triangles, a["ref"].cot)

    return EquilibriumSystem(force, scale, parts, admissible, bound, block_diag, update,
                             overflow, step_cap, laplacian, free)


# ------------------------------------------------------------------ compiled pieces
#: Solver settings passed to the compiled loop as traced values, so that solves that
#: differ only in them (a scene's rtol, the optimiser's trial cap) run one program.
TRACED_SETTINGS = ("rtol", "max_steps")


def _fill(solver, settings):
    """``solver`` with the fields in ``settings`` replaced, unvalidated (set to None for
    the static key of the compiled solve, or to tracers inside it)."""
    if not settings:
        return solver
    out = object.__new__(type(solver))
    out.__dict__.update(solver.__dict__)
    out.__dict__.update(settings)
    return out


def _split(solver, dtype):
    """(``solver`` with its `TRACED_SETTINGS` set to None, their values as arrays)."""
    vals = {k: getattr(solver, k) for k in TRACED_SETTINGS
            if isinstance(getattr(solver, k, None), (int, float, np.number))
            and not isinstance(getattr(solver, k), bool)}
    return _fill(solver, dict.fromkeys(vals)), {
        k: (np.asarray(v, np.int32) if isinstance(v, (int, np.integer))
            else np.asarray(v, dtype)) for k, v in vals.items()}


def _phases(solver):
    """The loops of a solve: a solver's warm starts, then the solver."""
    return tuple(getattr(solver, "warm_start", None) or ()) + (solver,)


def _args(problem, params, x0, extra):
    ref = assembly.prepare(problem, params)
    a = dict(params=params, ref=ref, f0=jnp.asarray(-1.0, x0.dtype), x_start=x0,
             escape=escape_distance(x0))
    return {**a, **extra}


#: `_args` as one program, for solves called from the host
_args_jit = jax.jit(_args)


@functools.partial(jax.jit, static_argnums=(0, 1, 2))
def _start(blank, i, contact, problem, settings, y, args):
    """The carry of loop ``i`` at y, for a solver that evaluates the force there first
    (FIRE builds its own, on the host: `base.start`)."""
    phase = _phases(_fill(blank, settings))[i]
    return start(phase, make_system(problem, contact), y, args)


@functools.partial(jax.jit, static_argnums=(0, 1, 2))
def _stretch(blank, i, contact, problem, settings, c, stop):
    """Loop ``i`` from carry c to at most ``stop`` steps: (carry, still running)."""
    phase = _phases(_fill(blank, settings))[i]
    c = run(phase, make_system(problem, contact), c, stop)
    return c, running(phase, c)


@functools.partial(jax.jit, static_argnums=(0, 1, 2))
def _residual(blank, i, contact, problem, settings, c):
    """The relative residual at a loop's end, for a solver that does not keep it."""
    return relative_residual(make_system(problem, contact), c.y, c.args, c.state.get("F"))


def _outcome(phase, c, residual):
    """(y, args, result, steps, residual, best state, its residual) of a finished carry."""
    y, args, st, result, n = end(c)
    return y, args, result, n, residual, st.get("best_y", y), st.get("rmin", residual)


def _run_traced(blank, contact, problem, settings, y, args):
    """Every loop of the solve in one trace (inside jit or vmap)."""
    solver = _fill(blank, settings)
    system = make_system(problem, contact)
    steps = jnp.asarray(0, jnp.int32)
    for phase in _phases(solver):
        c = run(phase, system, start(phase, system, y, args))
        res = (c.state["r"] if "r" in c.state
               else relative_residual(system, c.y, c.args, c.state.get("F")))
        y, args, result, n, res, best, rbest = _outcome(phase, c, res)
        steps = steps + n
    return y, args, result, steps, res, best, rbest


def _run_host(blank, contact, problem, settings, y, args, name):
    """Every loop of the solve, driven from the host in stretches of whole multiples of
    `progress.BEACON_EVERY` steps sized to their time (`progress.next_stretch`), a beacon
    after each: one compiled program a loop (FIRE's carry is made on the host)."""
    steps = 0
    for i, phase in enumerate(_phases(_fill(blank, settings))):
        if getattr(phase, "lazy_force", False):
            c = start(phase, None, y, args)
        else:
            c = _start(blank, i, contact, problem, settings, y, args)
        go, n, k = bool(running(phase, c)), 0, 1
        while go:
            n += k * progress.BEACON_EVERY
            t0 = time.perf_counter()
            c, go = _stretch(blank, i, contact, problem, settings, c, jnp.int32(n))
            go = bool(go)
            k = progress.next_stretch(k, time.perf_counter() - t0)
            r = c.state["r"] if "r" in c.state else jnp.nan
            progress.beacon(steps + int(c.n), r, type(phase).__name__)
        res = (c.state["r"] if "r" in c.state
               else _residual(blank, i, contact, problem, settings, c))
        y, args, result, k, res, best, rbest = _outcome(phase, c, res)
        steps += int(k)
    return y, args, result, jnp.asarray(steps), res, best, rbest


def _raise(result, residual, steps):
    code = int(result)
    if code != RESULTS.successful:
        r = RESULTS(code)
        raise ConvergenceError(f"equilibrium solve failed: {r.message} ({r.name}); relative "
                               f"residual {float(residual):.3e} after {int(steps)} steps")


def _check_inputs(problem, params, x0):
    x0 = jnp.asarray(x0)
    if x0.shape != (problem.n_nodes, 3):
        raise ParameterError(f"x0 must have shape ({problem.n_nodes}, 3); got {x0.shape}")
    if not isinstance(x0, jax.core.Tracer) and not np.all(np.isfinite(np.asarray(x0))):
        raise ParameterError("x0 holds a non-finite coordinate; every coordinate must be finite")
    validate_params(params)
    return x0, jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype=x0.dtype), params)


@functools.partial(jax.jit, static_argnums=(0,))
def _barrier_start(caps, dhat, ref, x0, topo):
    """(stale pair lists, collision weights) of a barrier solve from x0: one program
    rather than a compiled program for each array operation."""
    return (pair_lists.stale(x0, caps, dhat, SKIN, MARGIN),
            collision_weights(ref, topo.triangles, topo.tri_edge, int(topo.n_edges)))


def contact_args(problem, params, x0, topo=None, caps=None, dhat=None):
    """(Contact, args extra: empty pair lists that the solve builds at its first step,
    their topology, the collision weights) for a solve of ``params.contact``; the
    capacities ``caps`` or, where None, those for a closing valve of this mesh."""
    kind = _kind(params)
    if kind is None:
        return Contact(), {}
    if topo is None:
        topo = pair_lists.contact_topology(np.asarray(problem.triangles),
                                           np.asarray(problem.body),
                                           np.asarray(problem.fixed), np.asarray(x0))
    if kind == "barrier":
        law = params.contact
        if float(law.dhat) > topo.self_gap:
            raise ParameterError(f"the barrier's dhat = {float(law.dhat):g} mm must not exceed "
                                 f"the self-contact gap self_gap = {topo.self_gap:g} mm")
        caps = caps or pair_lists.Capacities.for_mesh(topo, law.dhat, SKIN, MARGIN)
        lists, weights = _barrier_start(caps, law.dhat, params.ref, x0, topo)
        return Contact("barrier", caps), dict(lists=lists, topo=topo, weights=weights)
    reach = float(1.25 * vicinity_threshold(jnp.asarray(x0), problem.triangles))
    caps = caps or pair_lists.Capacities.for_mesh(topo, reach, SKIN, 0.5)
    lists = pair_lists.stale(x0, caps, reach, SKIN, 0.5)
    return Contact("paper", caps), dict(lists=lists, topo=topo)


def finish(problem, params, engine: Engine, fire: Solution, best, rbest) -> Solution:
    """The engine's solve after its FIRE phase ``fire``: where FIRE stagnated or reached its
    cap, Newton on the exact tangent from FIRE's best state (``best``, its residual
    ``rbest`` < ``engine.finish_below``; `jaxvalve.solvers.finish`), else ``fire`` as it
    is."""
    if (int(fire.result) not in (RESULTS.stagnation, RESULTS.max_steps_reached)
            or not float(rbest) < engine.finish_below):
        return fire
    from .finish import newton_finish
    start_x = best if float(rbest) < float(fire.stats.residual) else fire.x
    return newton_finish(problem, params, start_x, engine, fire,
                         fire_steps=int(fire.stats.steps))


def fire_batch(problem, params, x0, engine: Engine, topo, caps):
    """The engine's FIRE phase for a batch of members in one compiled program (`jax.vmap`
    over the leading axis of every leaf of ``params`` and of x0 (B, N, 3)), the pair lists
    built inside it at the capacities ``caps``: (y (B, N, 3), result (B,), steps (B,),
    residual (B,), best state (B, N, 3), its residual (B,), overflow (B,), and the lists'
    needs: candidates (B, 4), active (B, 4), raw (B, 2)).  A batch whose lists overflowed
    is the caller's to run again with grown capacities (`Capacities.grown`)."""
    blank, settings = _split(engine.fire(), x0.dtype)
    contact = Contact("barrier", caps)
    return _fire_batch(blank, contact, problem, settings, params, x0, topo)


@functools.partial(jax.jit, static_argnums=(0, 1))
def _fire_batch(blank, contact, problem, settings, params, x0, topo):
    def one(p, x):
        law = p.contact
        lists = pair_lists.stale(x, contact.caps, law.dhat, SKIN, MARGIN)
        w = collision_weights(p.ref, topo.triangles, topo.tri_edge, int(topo.n_edges))
        args = _args(problem, p, x, dict(lists=lists, topo=topo, weights=w))
        y, a, result, steps, res, best, rbest = _run_traced(blank, contact, problem,
                                                            settings, x, args)
        lists = a["lists"]
        return (y, result, steps, res, best, rbest,
                pair_lists.overflow_flag(lists, contact.caps), lists.cand.need,
                lists.act.need, lists.raw)
    return jax.vmap(one)(params, x0)


def solve(problem: Problem, params: Params, x0, solver=None, *, throw: bool = True,
          topo=None, caps=None, start_lists=None) -> Solution:
    """Equilibrium of ``problem`` under ``params`` from x0 (N, 3) mm.

    solver: `NewtonKrylov()` (default without contact), `FIRE()`, `FixedPoint()` or, with
    the barrier contact, `Engine()` (its default).  throw: raise `ConvergenceError` unless
    the solve converged; with throw=False inspect ``solution.result``.  topo, caps: the
    contact topology (`jaxvalve.contact.pairs.contact_topology`, built from the problem
    and x0 where None) and starting list capacities.  The returned `Solution` carries the
    final pair lists (``lists``) and capacities (``caps``) for the adjoint and the next
    solve."""
    kind = _kind(params)
    if solver is None:
        solver = Engine() if kind == "barrier" else NewtonKrylov()
    x0, params = _check_inputs(problem, params, x0)
    engine = isinstance(solver, Engine)
    if engine and kind != "barrier":
        raise ParameterError("the Engine closes membranes with the barrier contact "
                             "(params.contact = BarrierContact())")
    if kind == "paper" and not isinstance(solver, FixedPoint):
        raise ParameterError("the paper's contact law is solved by FixedPoint (Algorithm 2.1)")
    loop_solver = solver.fire() if engine else solver
    traced = any(isinstance(v, jax.core.Tracer)
                 for v in jax.tree_util.tree_leaves((problem, params, x0)))
    for _ in range(8):
        contact, extra = contact_args(problem, params, x0, topo, caps)
        if kind == "paper":
            d = (solver.delta if solver.delta is not None else
                 1.0 / float(jnp.max(jnp.where(problem.free, assembly.stiffness_bound(
                     x0, problem, params, assembly.prepare(problem, params)), 0.0))))
            extra["delta"] = jnp.asarray(d, x0.dtype)
        args = (_args if traced else _args_jit)(problem, params, x0, extra)
        blank, settings = _split(loop_solver, x0.dtype)
        if traced:
            out = _run_traced(blank, contact, problem, settings, x0, args)
        else:
            out = _run_host(blank, contact, problem, settings, x0, args,
                            type(loop_solver).__name__)
        y, args, result, steps, res, best, rbest = out
        if traced or contact.kind is None or not pair_lists.overflowed(args["lists"],
                                                                       contact.caps):
            break
        lists = args["lists"]
        caps = contact.caps.grown(lists.cand.need, lists.act.need, lists.raw)
        topo = args["topo"]
    stats = Stats(steps=steps, force_evals=steps, hvps=jnp.asarray(0), residual=res)
    sol = Solution(x=y, result=result, stats=stats, lists=args.get("lists"),
                   caps=contact.caps, topo=args.get("topo"))
    if engine and not traced:
        sol = finish(problem, params, solver, sol, best, rbest)
    if throw:
        if isinstance(sol.result, jax.core.Tracer):
            jax.debug.callback(_raise, sol.result, sol.stats.residual, sol.stats.steps)
        else:
            _raise(sol.result, sol.stats.residual, sol.stats.steps)
    if kind != "paper" and (traced or int(sol.result) == RESULTS.successful):
        # x* as a differentiable function of params and x0: one adjoint solve, never the
        # solver's loop
        sol = dataclasses.replace(sol, x=adjoint.implicit_state(problem, params, x0, sol))
    return sol
