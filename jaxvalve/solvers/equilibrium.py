"""The public equilibrium solve, with its implicit (adjoint) derivative.

``solve(problem, params, x0)`` finds x with residual(x) = 0 on the free nodes, starting
from x0 (N, 3) mm; fixed nodes stay at x0.  Reverse-mode gradients of anything computed
from the returned x, with respect to ``params`` (material, H, P, ref, contact) and to the
fixed positions in x0, come from the implicit function theorem: one adjoint solve
K^T mu = g with the transposed stiffness, never from unrolling the iterations.
"""
from __future__ import annotations

import contextlib
import dataclasses
import functools
import logging
import time

import jax
import jax.numpy as jnp
import numpy as np

from . import adjoint
from ..mechanics import assembly
from ..contact.soft_pairs import (SoftPairs, build_soft_pairs, default_soft_capacity,
                                 stale_soft_pairs)
from ..contact.soft_pairs import refresh as refresh_soft
from ..contact.neighbours import whole_lists as one_prefix
from ..quick_jit import quick_jit
from ..errors import ConvergenceError, NeighbourListOverflow, ParameterError
from ..geometry.mesh import edge_lengths_np
from ..mechanics.problem import Params, Problem, validate_params
from .base import (RESULTS, EquilibriumSystem, Solution, Stats, iterate, loop_chunk, loop_end,
                   loop_residual, loop_running, loop_start)
from .. import progress
from .fixed_point import FixedPoint
from .newton import NewtonKrylov
from .base import escape_distance, relative_residual, set_f0
from .. import contact as _contact

_log = logging.getLogger("jaxvalve")

DEFAULT_SKIN = 1.0  # mm: pair lists are rebuilt once a node has moved skin / 2


def mesh_skin(triangles, ref) -> float:
    """Verlet skin (mm) for a mesh: its median edge length in the reference ``ref`` (N, 2|3)
    mm, rounded to 0.01 mm and at most `DEFAULT_SKIN`.  With the skin following the mesh
    size, a node's candidates (within g0 + skin) stay nearly as many triangles as the mesh
    is refined (they grow only through the fixed gap g0), so the broad phase is about
    linear in the triangles M; with a fixed 1 mm skin it grows like M^1.2-1.4
    (`benchmarks/skips.py`).  Rounded, so that a template change of one
    mesh does not change this static value (one compiled solve)."""
    e = edge_lengths_np(ref, triangles)
    return float(min(DEFAULT_SKIN, max(0.01, round(float(np.median(e)), 2))))


def contact_cutoff(contact, x, triangles, skin=DEFAULT_SKIN):
    """Broad-phase radius (mm): interaction range of the law plus the skin."""
    if hasattr(contact, "energy"):
        return float(contact.gap) + skin
    return 1.25 * float(_contact.vicinity_threshold(x, triangles)) + skin


def init_pairs(contact, problem, x, skin=DEFAULT_SKIN, capacity=None, soft_capacity=None):
    """Contact pair list for state x, grown outside jit until nothing overflows: the
    Verlet list, and for a soft-min law the pruned list over it (`soft_pairs`)."""
    cutoff = contact_cutoff(contact, jnp.asarray(x), problem.triangles, skin)
    base = _contact.build_neighbours_checked(x, problem.triangles, problem.body, cutoff,
                                             capacity=capacity)
    if not getattr(contact, "soft_min", False):
        return base
    cap = soft_capacity or default_soft_capacity(problem.n_nodes)
    for _ in range(12):
        pairs = _build_soft(base, jnp.asarray(x), problem.triangles, contact, cap)
        if not bool(pairs.soft_overflow):
            return pairs
        cap = max(2 * cap, int(pairs.soft_count))
    raise NeighbourListOverflow(f"the soft-min pair list needs {int(pairs.soft_count)} "
                                "slots; it could not be grown")


def stale_pairs(contact, problem, x, skin=DEFAULT_SKIN):
    """The empty pair list(s) of `init_pairs`'s default capacities, to be built by the
    solve's first update (`neighbours.stale_list`)."""
    cutoff = contact_cutoff(contact, jnp.asarray(x), problem.triangles, skin)
    base = _contact.stale_list(problem.n_nodes, problem.triangles, problem.body, cutoff,
                               dtype=jnp.asarray(x).dtype)
    if not getattr(contact, "soft_min", False):
        return base
    return stale_soft_pairs(base, default_soft_capacity(problem.n_nodes))


@quick_jit(static_argnums=(4,))
def _build_soft(base, x, triangles, contact, capacity):
    """The pruned pair list at a solve's start, compiled for compile time (it runs once
    per solve): on the whole candidate list, with `quick_jit`'s CPU emitters."""
    with one_prefix():
        return build_soft_pairs(base, x, triangles, contact, capacity)


@jax.jit
def _refresh(pairs, x, triangles, body, skin, contact):
    return refresh_soft(pairs, x, triangles, body, skin, contact)


def update_pairs(nbrs, x, problem, skin, contact):
    """Bring a pair list (either level) up to date at x (usable inside jit)."""
    if isinstance(nbrs, SoftPairs):
        return refresh_soft(nbrs, x, problem.triangles, problem.body, skin, contact)
    return _contact.update(nbrs, x, problem.triangles, problem.body, skin)


def make_system(problem: Problem, params: Params) -> EquilibriumSystem:
    """The functions a solver needs, with ``args = dict(params, ref, nbrs, delta, f0)``."""
    contact = params.contact

    def force(y, a):
        return assembly.residual(y, problem, a["params"], a["ref"], a["nbrs"], a["delta"])

    def scale(y, a):
        p = a["params"]
        return jnp.where(p.pressure != 0, assembly.pressure_scale(y, problem, p), a["f0"])

    def force_scale(y, a):
        p = a["params"]
        F, s = assembly.residual_and_scale(y, problem, p, a["ref"], a["nbrs"], a["delta"])
        return F, jnp.where(p.pressure != 0, s, set_f0(a, F)["f0"])

    def admissible(y, a):
        return assembly.stretch_admissible(y, problem, a["params"], a["ref"])

    def bound(y, a):
        return assembly.stiffness_bound(y, problem, a["params"], a["ref"])

    def block_diag(y, a):
        return assembly.block_diagonal(y, problem, a["params"], a["ref"])

    def update(y, a):
        if contact is None:
            return a
        return dict(a, nbrs=update_pairs(a["nbrs"], y, problem, a["skin"],
                                         a["params"].contact))

    def overflow(a):
        if contact is None:
            return jnp.asarray(False)
        return a["nbrs"].overflow

    def laplacian(v, a):
        return assembly.laplacian_apply(v, problem.triangles, a["ref"].cot)

    return EquilibriumSystem(force, scale, admissible, bound, block_diag, update, overflow,
                             laplacian, problem.free, force_scale)


def _make_args(problem, params, x0, nbrs, solver, skin):
    ref = assembly.prepare(problem, params)
    has_contact = params.contact is not None
    a = dict(params=params, ref=ref, nbrs=nbrs, delta=jnp.asarray(0.0, x0.dtype),
             f0=jnp.asarray(1.0, x0.dtype), skin=jnp.asarray(skin, x0.dtype),
             max_move=jnp.asarray(0.5 * skin if has_contact else jnp.inf, x0.dtype),
             x_start=x0, escape=escape_distance(x0))
    system = make_system(problem, params)
    if params.contact is not None and hasattr(params.contact, "force"):
        # the paper's law needs the fixed-point step delta (tentative positions)
        d = (solver.delta if isinstance(solver, FixedPoint) and solver.delta is not None
             else 1.0 / jnp.max(jnp.where(problem.free, system.bound(x0, a), 0.0)))
        a = dict(a, delta=jnp.asarray(d, x0.dtype))
    # f0 (the residual scale at P = 0) is set from the first solver's initial force
    # (`iterate`), so the force is not traced once more here
    a = dict(a, f0=jnp.asarray(-1.0, x0.dtype))
    return system, a


def _run(solver, problem, params, x0, nbrs, skin):
    """The solve as one program: (y, result, `Stats`, pair list, delta)."""
    system, args = _make_args(problem, params, x0, nbrs, solver, skin)
    totals = (jnp.asarray(0),) * 3
    y = x0
    for warm in getattr(solver, "warm_start", None) or ():
        y, args, st, _, n = iterate(warm, system, y, args)
        args, totals = _warm_done(warm, system, y, args, st, n, totals)
    y, args, st, result, n = iterate(solver, system, y, args)
    return _finish(solver, system, y, args, st, result, n, *totals)


def _warm_done(warm, system, y, args, st, n, totals):
    """After a warm start's loop: the args brought up to date at y, and the totals
    (steps, force evaluations, Hessian-vector products) with its own added."""
    s = warm.stats(st)
    return system.update(y, args), (totals[0] + n, totals[1] + s["force_evals"],
                                    totals[2] + s["hvps"])


def _finish(solver, system, y, args, st, result, n, steps, evals, hvps):
    """The solve's output (y, result, `Stats`, pair list, delta) after its last loop;
    steps, evals, hvps: those of the warm starts before it."""
    s = solver.stats(st)
    # every solver keeps the force at its current state: no extra traced force evaluation
    res = relative_residual(system, y, args, st["F"] if "F" in st else None)
    if getattr(solver, "lazy_force", False):   # no step ran: F(x0) was never evaluated
        res = jnp.where(n > 0, res, jnp.inf)
    stats = Stats(steps=steps + n, force_evals=evals + s["force_evals"], hvps=hvps + s["hvps"],
                  residual=res)
    return y, result, stats, args["nbrs"], args["delta"]


#: Solver settings that reach the compiled solve as traced values, not as part of the
#: static solver: solves that differ only in their tolerance or step cap (a scene's
#: rtol, the optimiser's trial cap, the stress suite's cap) run one compiled program.
#: In the test suite the same FIRE loop was otherwise compiled once per setting
#: (1.4-24 s a compile).  The other settings shape the program (FIRE's patience traces its
#: residual; FixedPoint's delta) and stay static.
TRACED_SETTINGS = ("rtol", "max_steps")


def _fill(solver, settings):
    """``solver`` with the fields in ``settings`` replaced, unvalidated: set to None for
    the static key of the compiled solve, or to tracers inside it."""
    if not settings:
        return solver
    out = object.__new__(type(solver))
    out.__dict__.update(solver.__dict__)
    out.__dict__.update(settings)
    return out


def _setting_args(solver, dtype):
    """(``solver`` with its `TRACED_SETTINGS` set to None, their values as arrays: float
    settings in the state's dtype, counts int32)."""
    vals = {k: getattr(solver, k) for k in TRACED_SETTINGS
            if isinstance(getattr(solver, k, None), (int, float, np.number))
            and not isinstance(getattr(solver, k), bool)}
    return _fill(solver, dict.fromkeys(vals)), {
        k: (np.asarray(v, np.int32) if isinstance(v, (int, np.integer))
            else np.asarray(v, dtype)) for k, v in vals.items()}


@functools.partial(jax.custom_vjp, nondiff_argnums=(0, 5))
def _equilibrium(blank, problem, params, x0, nbrs, skin, settings):
    return _run(_fill(blank, settings), problem, params, x0, nbrs, skin)


def _eq_fwd(blank, problem, params, x0, nbrs, skin, settings):
    out = _equilibrium(blank, problem, params, x0, nbrs, skin, settings)
    y, _, _, nb, delta = out
    return out, (problem, params, y, nb, delta, settings)


def _zeros_like(t):
    return jax.tree_util.tree_map(
        lambda a: (None if not jnp.issubdtype(jnp.asarray(a).dtype, jnp.inexact)
                   else jnp.zeros_like(a)), t)


def _eq_bwd(blank, skin, res, cts):
    problem, params, y, nb, delta, settings = res
    gp, gx0 = adjoint.cotangents(problem, params, y, nb, delta, cts[0])
    return (_zeros_like(problem), gp, gx0, _zeros_like(nb), _zeros_like(settings))


_equilibrium.defvjp(_eq_fwd, _eq_bwd)


def _solve_jit(solver, problem, params, x0, nbrs, skin, whole_lists=False):
    """The compiled solve: ``solver``'s `TRACED_SETTINGS` as arguments, the rest static.
    Called with concrete values it runs from the host in stretches (`_solve_stretches`);
    inside a trace (jit, grad, vmap) it is one program (`_solve_compiled`)."""
    blank, settings = _setting_args(solver, jnp.asarray(x0).dtype)
    if any(isinstance(v, jax.core.Tracer)
           for v in jax.tree_util.tree_leaves((problem, params, x0, nbrs))):
        return _solve_compiled(blank, problem, params, x0, nbrs, skin, whole_lists, settings)
    return _solve_stretches(blank, problem, params, x0, nbrs, skin, whole_lists, settings)


def _solve_stretches(blank, problem, params, x0, nbrs, skin, whole_lists, settings):
    """`_run` driven from the host: each solver's loop (the warm starts', then the
    solver's) runs in compiled stretches of whole multiples of `progress.BEACON_EVERY`
    steps (`progress.next_stretch`: one at first, then grown until a stretch lasts about
    `progress.STRETCH_S`), and the host sends the beacon after each.  Where a stretch ends
    does not change the solve: the loop's carry passes through unchanged.  The same loop
    body as `_solve_compiled`'s, but no host callback in any program, so that JAX's
    persistent compilation cache keeps them (it stores no program that holds one: a warm
    `jaxvalve simulate` compiled its solve anew, 16.8 s of compilation against 5.8 s
    without the callback)."""
    n_phases = len(getattr(blank, "warm_start", None) or ()) + 1
    args = _stretch_args(blank, problem, params, x0, nbrs, skin, whole_lists, settings)
    y, totals = x0, (jnp.asarray(0),) * 3
    every = progress.BEACON_EVERY
    for i in range(n_phases):
        name = type(_phase(blank, settings, i)).__name__
        c, running = _stretch_start(blank, i, problem, params, skin, whole_lists, settings,
                                    y, args)
        n, k = int(c[3]), 1
        while bool(running):
            t = time.perf_counter()
            c, running, res = _stretch(blank, i, problem, params, skin, whole_lists,
                                       settings, c, jnp.asarray((n // every + k) * every))
            n = int(c[3])
            if n % every == 0:
                progress.beacon(n, res, name)
            k = progress.next_stretch(k, time.perf_counter() - t)
        out = _stretch_end(blank, i, problem, params, skin, whole_lists, settings, c, totals)
        if i + 1 < n_phases:
            y, args, totals = out
    return out


def _phase(blank, settings, i):
    """The solver of loop ``i`` of a solve: the warm starts in turn, then the solver."""
    warm = tuple(getattr(blank, "warm_start", None) or ())
    return warm[i] if i < len(warm) else _fill(blank, settings)


def _lists(whole_lists):
    return one_prefix() if whole_lists else contextlib.nullcontext()


@functools.partial(jax.jit, static_argnums=(0, 5, 6))
def _stretch_args(blank, problem, params, x0, nbrs, skin, whole_lists, settings):
    with _lists(whole_lists):
        return _make_args(problem, params, x0, nbrs, _fill(blank, settings), skin)[1]


@functools.partial(jax.jit, static_argnums=(0, 1, 4, 5))
def _stretch_start(blank, i, problem, params, skin, whole_lists, settings, y, args):
    solver = _phase(blank, settings, i)
    with _lists(whole_lists):
        c = loop_start(solver, make_system(problem, params), y, args)
    return c, loop_running(solver, c)


@functools.partial(jax.jit, static_argnums=(0, 1, 4, 5))
def _stretch(blank, i, problem, params, skin, whole_lists, settings, c, stop):
    solver = _phase(blank, settings, i)
    system = make_system(problem, params)
    with _lists(whole_lists):
        c = loop_chunk(solver, system, c, stop)
        return c, loop_running(solver, c), loop_residual(system, c)


@functools.partial(jax.jit, static_argnums=(0, 1, 4, 5))
def _stretch_end(blank, i, problem, params, skin, whole_lists, settings, c, totals):
    """A warm start's (y, args, totals) for the next loop, or the solve's output; totals:
    the steps, force evaluations and Hessian-vector products of the loops before
    (`_warm_done`)."""
    solver = _phase(blank, settings, i)
    system = make_system(problem, params)
    y, args, st, result, n = loop_end(c)
    with _lists(whole_lists):
        if i < len(getattr(blank, "warm_start", None) or ()):
            return (y, *_warm_done(solver, system, y, args, st, n, totals))
        return _finish(solver, system, y, args, st, result, n, *totals)


@functools.partial(jax.jit, static_argnums=(0, 5, 6))
def _solve_compiled(blank, problem, params, x0, nbrs, skin, whole_lists, settings):
    with one_prefix() if whole_lists else contextlib.nullcontext():
        return _equilibrium(blank, problem, params, x0, nbrs, skin, settings)


@quick_jit(static_argnums=(6,))
def _recheck(problem, params, x0, y, nbrs, delta, at_rest):
    """(relative residual, state sound) of a solve's result y (N, 3) mm, from a program of
    its own: the force, the residual scale (||F_pressure||, or ||F(x0)|| at rest, P = 0)
    and the stretch and finiteness checks evaluated afresh, none of them read from the
    solver's loop.  The program runs once per solve, at one state, so it is compiled for
    compile time: traced on the whole pair lists (`contact.neighbours.whole_lists`; the
    solver's switch over list prefixes would only add branches) and with `quick_jit`'s
    CPU emitters (`python benchmarks/recheck_compile.py`)."""
    ref = assembly.prepare(problem, params)
    with one_prefix():
        F = assembly.residual(y, problem, params, ref, nbrs, delta)
        if at_rest:
            scale = jnp.linalg.norm(assembly.residual(x0, problem, params, ref, nbrs, delta))
    if not at_rest:
        scale = assembly.pressure_scale(y, problem, params)
    res = jnp.linalg.norm(F) / jnp.where(scale > 0, scale, 1.0)
    sound = (assembly.stretch_admissible(y, problem, params, ref)
             & jnp.all(jnp.isfinite(y)) & jnp.all(jnp.isfinite(F)))
    return res, sound


def recheck(solver, problem, params, x0, y, nbrs, delta, residual):
    """None when the converged result y agrees with an independent evaluation, else the
    independent relative residual (inf where the state is not sound).  Agreement: the
    state is finite and inside the stretch limit, and the fresh residual is below twice
    the solver's stopping threshold ``rtol`` (a solver that stops on its step length, the
    paper's fixed point, has none: then within twice the loop's own residual), or below
    1000 rounding units."""
    res, sound = _recheck(problem, params, x0, y, nbrs, delta, float(params.pressure) == 0)
    res = float(res)
    eps = float(jnp.finfo(y.dtype).eps)
    rtol = getattr(solver, "rtol", None)
    tol = 2.0 * max(float(residual) if rtol is None else float(rtol), 500 * eps)
    if bool(sound) and res <= tol:
        return None
    return res if bool(sound) else float("inf")


@contextlib.contextmanager
def _fresh_compilation():
    """Drop every compiled program held in memory and bypass the persistent compilation
    cache, so that what runs in this block is compiled anew."""
    jax.clear_caches()
    on = jax.config.jax_enable_compilation_cache
    jax.config.update("jax_enable_compilation_cache", False)
    try:
        yield
    finally:
        jax.config.update("jax_enable_compilation_cache", on)


def _raise_host(code, residual, steps):
    code = int(code)
    if code != RESULTS.successful:
        r = RESULTS(code)
        raise ConvergenceError(f"equilibrium solve failed: {r.message} ({r.name}); relative "
                               f"residual {float(residual):.3e} after {int(steps)} steps")


def solve(problem: Problem, params: Params, x0, solver=None, *, throw: bool = True,
          nbrs=None, skin: float = DEFAULT_SKIN, whole_lists: bool = False) -> Solution:
    """Equilibrium of ``problem`` under ``params`` from the start x0 (N, 3) mm.

    solver: `NewtonKrylov()` (default), `FIRE()` or `FixedPoint()` (Algorithm 2.1).
    throw: raise `ConvergenceError` (with the residual) unless the solve converged; with
    throw=False the caller must inspect ``solution.result``.
    nbrs, skin: contact pair list (built here at x0 when None, else brought up to date
    at x0) and its skin (mm; a valve's closures pass `Valve.skin`).  A pair list
    that overflows inside the solve is rebuilt here at a larger capacity and the solve
    is repeated.  Differentiable in reverse
    mode with respect to params and the fixed positions in x0 (implicit adjoint).
    whole_lists: evaluate contact on the whole pair lists (`contact.whole_lists`) instead
    of the shortest of up to three prefixes that holds the pairs in use.  Same values;
    about 6 s less compilation at h = 0.88 mm, as fast where most of the lists are in
    use (closures at 80 mmHg), slower where few pairs are live (at 3 mmHg: 1.2-1.5x).
    """
    solver = NewtonKrylov() if solver is None else solver
    if not isinstance(whole_lists, bool):
        raise ParameterError(f"whole_lists must be True or False; got {whole_lists!r}")
    x0 = jnp.asarray(x0)
    if x0.shape != (problem.n_nodes, 3):
        raise ParameterError(f"x0 must have shape ({problem.n_nodes}, 3); got {x0.shape}")
    if not isinstance(x0, jax.core.Tracer) and not np.all(np.isfinite(np.asarray(x0))):
        raise ParameterError("x0 holds a non-finite coordinate; every coordinate must be finite")
    validate_params(params)
    # strong float64 leaves: a Python float and an array then share one compiled solve
    params = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype=x0.dtype), params)
    # a solver that updates the pair list before its first force evaluation builds it in
    # the solve (compiled once there), from an empty list; the others get it built here
    lazy = getattr((getattr(solver, "warm_start", None) or (solver,))[0], "lazy_force", False)
    if params.contact is not None and nbrs is None and lazy:
        nbrs = stale_pairs(params.contact, problem, x0, skin)
    elif params.contact is not None and nbrs is None:
        nbrs = init_pairs(params.contact, problem, x0, skin)
    elif params.contact is not None and not lazy:
        # the solve assumes a pair list current at x0
        nbrs = (_refresh(nbrs, x0, problem.triangles, problem.body, skin, params.contact)
                if isinstance(nbrs, SoftPairs)
                else _contact.update(nbrs, x0, problem.triangles, problem.body, skin))
    for _ in range(6):
        y, result, stats, nb, delta = _solve_jit(solver, problem, params, x0, nbrs,
                                                 float(skin), bool(whole_lists))
        if isinstance(result, jax.core.Tracer) or int(result) != RESULTS.neighbour_overflow:
            break
        soft = isinstance(nb, SoftPairs)
        base = nb.base if soft else nb
        cap = nbrs.capacity
        if bool(base.overflow):
            cap = 2 * max(nbrs.capacity, int(base.count))
        soft_cap = None
        if soft:
            soft_cap = nbrs.soft_capacity
            if bool(nb.soft_overflow):
                soft_cap = 2 * max(soft_cap, int(nb.soft_count))
        nbrs = init_pairs(params.contact, problem, x0, skin, capacity=cap,
                          soft_capacity=soft_cap)
    if not isinstance(result, jax.core.Tracer) and int(result) == RESULTS.successful:
        y, result, stats, nb = _verified(solver, problem, params, x0, nbrs, float(skin),
                                         bool(whole_lists), (y, result, stats, nb, delta))
    sol = Solution(x=y, result=result, stats=stats, nbrs=nb)
    if throw:
        if isinstance(result, jax.core.Tracer):
            jax.debug.callback(_raise_host, result, stats.residual, stats.steps)
        else:
            _raise_host(result, stats.residual, stats.steps)
    return sol


def _verified(solver, problem, params, x0, nbrs, skin, whole_lists, out):
    """A converged solve's output (y, result, stats, nbrs), checked by `recheck`.  On a
    disagreement the solve is compiled anew and run once more (the test suite's machine
    has returned such results from compiled loops, docs/known-limits.md); if the rerun
    disagrees too, its result becomes `RESULTS.inconsistent` with the independent
    residual, never a silent equilibrium."""
    y, result, stats, nb, delta = out
    bad = recheck(solver, problem, params, x0, y, nb, delta, stats.residual)
    if bad is None:
        return y, result, stats, nb
    _log.warning("equilibrium: the solver reported convergence at relative residual %.3e, "
                 "an independent evaluation of its result gives %.3e; compiling the solve "
                 "anew and running it again", float(stats.residual), bad)
    with _fresh_compilation():
        y, result, stats, nb, delta = _solve_jit(solver, problem, params, x0, nbrs, skin,
                                                 whole_lists)
        if int(result) != RESULTS.successful:
            return y, result, stats, nb
        bad = recheck(solver, problem, params, x0, y, nb, delta, stats.residual)
    if bad is None:
        _log.warning("equilibrium: the recompiled solve agrees with the independent "
                     "evaluation (relative residual %.3e)", float(stats.residual))
        return y, result, stats, nb
    stats = dataclasses.replace(stats, residual=jnp.asarray(bad, stats.residual.dtype))
    return y, jnp.asarray(RESULTS.inconsistent, jnp.asarray(result).dtype), stats, nb


@jax.custom_vjp
def _implicit(problem, params, x0, x, nbrs, delta):
    return jnp.where(problem.fixed[:, None], x0, x)


def _implicit_fwd(problem, params, x0, x, nbrs, delta):
    y = _implicit(problem, params, x0, x, nbrs, delta)
    return y, (problem, params, y, nbrs, delta)


def _implicit_bwd(res, g):
    problem, params, y, nb, delta = res
    gp, gx0 = adjoint.cotangents(problem, params, y, nb, delta, g)
    return (_zeros_like(problem), gp, gx0, jnp.zeros_like(y), _zeros_like(nb),
            jnp.zeros_like(delta))


_implicit.defvjp(_implicit_fwd, _implicit_bwd)


def implicit_state(problem: Problem, params: Params, x0, solution: Solution):
    """The converged ``solution.x`` (N, 3) mm of ``solve(problem, params, x0, ...)`` as a
    differentiable function of ``params`` and of the fixed positions in x0, without
    running the solver again: the value is ``solution.x`` (fixed nodes taken from x0), and
    the reverse-mode derivative is `solve`'s implicit adjoint (one solve K^T mu = g).

    Use it to split a forward solve (run once, on the host) from a gradient evaluation
    that compiles only the adjoint.  The caller guarantees that ``solution`` converged for
    these params and fixed positions: a solution that did not converge raises
    `ConvergenceError` here (the adjoint of a non-equilibrium is meaningless)."""
    if params.contact is not None and hasattr(params.contact, "force"):
        raise ParameterError("implicit_state needs a differentiable contact law "
                             "(SmoothContact); the paper's law has no adjoint")
    if not isinstance(solution.result, jax.core.Tracer):
        _raise_host(solution.result, solution.stats.residual, solution.stats.steps)
    params = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype=solution.x.dtype), params)
    return _implicit(problem, params, jnp.asarray(x0), jax.lax.stop_gradient(solution.x),
                     solution.nbrs, jnp.asarray(0.0, solution.x.dtype))
