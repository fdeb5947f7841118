"""The engine's Newton finish: Newton on the exact tangent from FIRE's best state.

FIRE stalls where the coapted leaflets have a nearly free sliding mode: its residual falls
to 1e-3 - 1e-2 and wanders.  Newton resolves that mode at once.  Each step:

1. Direction: K d = F with K = -dF/dx the exact tangent (`jaxvalve.solvers.tangent`),
   by a sparse LU (scipy's SuperLU); in a backtracking step that fails,
   Levenberg-Marquardt damping (K + mu diag|K|) d = F, mu raised tenfold until a step
   succeeds and lowered after each success.
2. Length: at most ``max_move`` mm for a node and what the pair lists allow
   (`jaxvalve.contact.pairs.Lists.step_cap`), then the largest fraction that additive
   CCD (Li, Kaufman and Jiang 2021) proves free of contact on the candidate pairs
   (`ccd_fraction`): the leaflets never meet.
3. Acceptance by a watchdog (`newton_finish`): full steps while the residual comes back
   below the reference's within a few steps, else backtracking from the reference; every
   trial state must be admissible (finite, inside the material's stretch limit).

It runs on the host, around jitted kernels, for the members of a batch in turn; it stops
at ``rtol``, as `RESULTS.stagnation` when no damping gives a step that lowers the
residual or its best residual has not halved for a few steps, or at its step cap.
"""
from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .. import progress
from ..contact import pairs as pair_lists
from .base import RESULTS, Solution, Stats, escaped
from .tangent import Tangent

__all__ = ["newton_finish", "ccd_fraction"]

#: the fraction of its gap a pair may close in one step (additive CCD's s = 0.1)
CCD_KEEP = 0.1


def ccd_fraction(x, d, pairs, iters: int = 24):
    """The largest t in [0, 1] such that no pair of ``pairs`` (a `PairList`) closes more
    than 1 - `CCD_KEEP` of its gap along x + t d (x, d (N, 3) mm): additive CCD, each
    pair advanced by steps its distance proves safe (l_k bounds how fast its distance can
    shrink: the largest move of one side plus the other's, about the pair's mean move),
    ``iters`` advances at most (a pair still short of its bound keeps the safe t it
    reached).  Conservative by construction: d_k(t) >= d_k(t_i) - l_k (t - t_i) > 0."""
    def bound(rows, n, split, dist2):
        valid = jnp.arange(rows.shape[0]) < n
        xr, dr = x[rows], d[rows]
        rel = dr - jnp.mean(dr, axis=1, keepdims=True)
        sp_ = jnp.linalg.norm(rel, axis=-1)
        lp = jnp.max(sp_[:, :split], 1) + jnp.max(sp_[:, split:], 1)
        d0 = jnp.sqrt(dist2(xr))
        lp = jnp.where(valid & (lp > 0), lp, 1.0)
        d0 = jnp.where(valid, d0, 1.0)
        at = lambda t: xr + t[:, None, None] * dr

        def trip(c):
            i, t, done = c
            dt = (1.0 - CCD_KEEP) * jnp.sqrt(dist2(at(t))) / lp
            t1 = jnp.minimum(t + dt, 1.0)
            hit = jnp.sqrt(dist2(at(t1))) < CCD_KEEP * d0
            t_new = jnp.where(done | hit, t, t1)
            return i + 1, t_new, done | hit | (t_new >= 1.0)

        # a pair that cannot close (1 - CCD_KEEP) of its gap in the whole step is done at
        # t = 1 before the first advance; the loop runs while any pair is not done
        done0 = ~valid | ((1.0 - CCD_KEEP) * d0 >= lp)
        t0 = jnp.where(done0, 1.0, 0.0)
        _, t, _ = jax.lax.while_loop(lambda c: (c[0] < iters) & ~jnp.all(c[2]), trip,
                                     (jnp.int32(0), t0, done0))
        return jnp.min(jnp.where(valid, t, 1.0), initial=1.0)

    t_pt = bound(pairs.pt, pairs.n_pt, 1, pair_lists.pt_distance2_of)
    t_ee = bound(pairs.ee, pairs.n_ee, 2, pair_lists.ee_distance2_of)
    return jnp.minimum(t_pt, t_ee)


def _reselect(args, x):
    """The active pairs re-selected from the candidates at x where a node has moved
    margin / 2 since their selection (the candidates are rebuilt on the host, `_valid`)."""
    lists = args["lists"]
    need = pair_lists._moved(lists.act, x) >= 0.5 * lists.margin
    act = jax.lax.cond(need, lambda l: pair_lists.prune(
        l.cand, x, l.dhat + l.margin, l.act.pt.shape[0], l.act.ee.shape[0]),
        lambda l: l.act, lists)
    return dict(args, lists=dataclasses.replace(lists, act=pair_lists._sticky(act, lists.act)))


@functools.partial(jax.jit, static_argnums=(4,))
def _evaluate(x, problem, params, args, contact):
    """(force (N, 3), relative residual, admissible, args with the active pairs current
    at x).  The candidates must be valid at x (`_valid`)."""
    from .equilibrium import make_system
    system = make_system(problem, contact)
    args = _reselect(args, x)
    F, scale, _, _ = system.parts(x, args)
    ok = system.admissible(x, args) & jnp.all(jnp.isfinite(x)) & jnp.all(jnp.isfinite(F))
    return F, jnp.linalg.norm(F) / jnp.where(scale > 0, scale, 1.0), ok, args


@functools.partial(jax.jit, static_argnums=(3,))
def _rebuild(topo, ref, x, caps, lists):
    """Both levels rebuilt at x (the candidates' skin spent: rare in a finish)."""
    new = pair_lists.start(topo, ref, x, caps, lists.dhat, lists.skin, lists.margin)
    return dataclasses.replace(new, cand=pair_lists._sticky(new.cand, lists.cand),
                               act=pair_lists._sticky(new.act, lists.act),
                               raw=jnp.maximum(new.raw, lists.raw))


def _valid(args, x, caps, ref):
    """args with candidates valid at x: rebuilt where a node has moved (skin - margin) / 2
    since their build."""
    lists = args["lists"]
    moved = float(pair_lists._moved(lists.cand, x))
    if moved < 0.5 * float(lists.skin - lists.margin):
        return args
    return dict(args, lists=_rebuild(args["topo"], ref, x, caps, lists))


@jax.jit
def _safe_fraction(x, d, lists, max_move):
    """The largest step fraction along d: ``max_move`` for any node, the pair lists' cap
    and the CCD bound on the candidate pairs."""
    big = jnp.max(jnp.linalg.norm(d, axis=-1))
    cap = jnp.minimum(max_move, lists.candidate_cap(x))
    t0 = jnp.minimum(1.0, cap / jnp.where(big > 0, big, 1.0))
    return t0 * ccd_fraction(x, t0 * d, lists.cand)


@dataclasses.dataclass(frozen=True)
class _Settings:
    max_move: float = 1.0
    halvings: int = 8
    mu0: float = 1e-6
    mu_max: float = 1e3
    watch: int = 5
    patience: int = 8


def _direction(tangent, x, F, params, args, free, mu):
    """The step d (N, 3) mm of (K + mu diag|K|) d = F on the free dofs, or None where the
    matrix is singular."""
    K = tangent.matrix(x, params, args["lists"].act, args["weights"])
    if mu > 0:
        K = K + mu * sp.diags(np.abs(K.diagonal()) + 1e-300)
    try:
        dfree = spla.splu(K.tocsc(), permc_spec="MMD_AT_PLUS_A").solve(
            np.asarray(F)[free].reshape(-1))
    except RuntimeError:                                   # singular
        return None
    d = np.zeros(x.shape, np.asarray(x).dtype)
    d[free] = dfree.reshape(-1, 3)
    return jnp.asarray(d, x.dtype)


def newton_finish(problem, params, x0, engine, fire: Solution, fire_steps: int = 0,
                  settings: _Settings = _Settings()) -> Solution:
    """Newton from x0 (FIRE's best state) to ``engine.rtol``, at most
    ``engine.newton_steps`` steps; ``fire``: FIRE's `Solution` (its pair lists, capacities
    and topology).  Returns the finish's `Solution` (its steps those of both phases).

    Globalised by a watchdog (Chamberlain et al. 1982): up to ``settings.watch`` full
    (CCD-safe) Newton steps are taken whatever their residual, and kept once one lands
    below the reference state's residual; otherwise the finish returns to the reference
    and backtracks there (halving the step, then raising the damping mu).  A monotone
    line search alone stalls where the residual's curvature along a soft mode makes the
    full step's residual large although its state is close: the next step then converges.
    It stops as `RESULTS.stagnation` once its best residual has not halved for
    ``settings.patience`` steps (near a regular equilibrium Newton halves it every step).
    """
    from .equilibrium import Contact, _args_jit, _barrier_start
    contact = Contact("barrier", fire.caps)
    tangent = Tangent(problem)
    free = np.asarray(problem.free)
    topo = fire.topo
    weights = _barrier_start(fire.caps, params.contact.dhat, params.ref, x0, topo)[1]
    base = _args_jit(problem, params, jnp.asarray(x0), dict(lists=fire.lists, topo=topo,
                                                            weights=weights))
    x = jnp.asarray(x0)
    base = _valid(base, x, contact.caps, params.ref)
    F, res, ok, args = _evaluate(x, problem, params, base, contact)
    x_start, escape = jnp.asarray(fire.x), base["escape"]
    res = float(res)
    ref = (x, F, res, args)                # the reference: the lowest residual so far
    mu, watched, steps, result = 0.0, 0, 0, RESULTS.max_steps_reached
    mark, halved_at = res, 0               # patience: the step the residual last halved

    def trial(x, d, t, args):
        xt = x + t * d
        at = _valid(args, xt, contact.caps, params.ref)
        Ft, rt, okt, at = _evaluate(xt, problem, params, at, contact)
        return xt, Ft, float(rt), at, bool(okt) and np.isfinite(float(rt))

    for steps in range(engine.newton_steps + 1):
        progress.beacon(fire_steps + steps, ref[2], "Newton")
        if res < engine.rtol:
            ref = (x, F, res, args)
            result = RESULTS.successful
            break
        if not ok or not np.isfinite(res):
            result = RESULTS.nonfinite
            break
        if pair_lists.overflowed(args["lists"], contact.caps) or steps == engine.newton_steps:
            result = (RESULTS.neighbour_overflow if steps < engine.newton_steps
                      else RESULTS.max_steps_reached)
            break
        if ref[2] < 0.5 * mark:
            mark, halved_at = ref[2], steps
        elif steps - halved_at > settings.patience:
            result = RESULTS.stagnation
            break
        tried = None                      # (direction, full step) already tried at ref
        if watched < settings.watch:
            d = _direction(tangent, x, F, params, args, free, 0.0)
            if d is not None:
                t = float(_safe_fraction(x, d, args["lists"], settings.max_move))
                xt, Ft, rt, at, okt = trial(x, d, t, args)
                if okt:
                    x, F, res, args = xt, Ft, rt, at
                    watched += 1
                    if res < (1.0 - 1e-4) * ref[2]:
                        ref, watched = (x, F, res, args), 0
                    continue
                if watched == 0 and mu == 0.0:
                    tried = (d, t)
        # the watchdog is spent: back to the reference, and backtrack from there
        x, F, res, args = ref
        watched = settings.watch          # monotone until a step is accepted
        moved = False
        while not moved and mu <= settings.mu_max:
            if tried is not None:         # the full step from here failed: halve it
                (d, t), tried = tried, None
                t *= 0.5
            else:
                d = _direction(tangent, x, F, params, args, free, mu)
                if d is None:
                    mu = max(10.0 * mu, settings.mu0)
                    continue
                t = float(_safe_fraction(x, d, args["lists"], settings.max_move))
            for _ in range(settings.halvings):
                xt, Ft, rt, at, okt = trial(x, d, t, args)
                if okt and rt < (1.0 - 1e-4 * t) * res:
                    x, F, res, args, moved = xt, Ft, rt, at, True
                    break
                t *= 0.5
            if not moved:
                mu = max(10.0 * mu, settings.mu0)
        if not moved:
            result = RESULTS.stagnation
            break
        ref, watched = (x, F, res, args), 0
        mu = mu / 10.0 if mu > settings.mu0 else 0.0
        if bool(escaped(x, x_start, escape)):
            result = RESULTS.escaped
            break
    if result != RESULTS.successful:
        x, F, res, args = ref
    stats = Stats(steps=jnp.asarray(fire_steps + steps), force_evals=jnp.asarray(
        fire_steps + steps), hvps=jnp.asarray(0), residual=jnp.asarray(res))
    return Solution(x=x, result=jnp.asarray(int(result)), stats=stats, lists=args["lists"],
                    caps=contact.caps, topo=topo, newton_steps=steps)
