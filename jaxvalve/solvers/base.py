"""Result codes, the solution record, the equilibrium system and the one driver loop.

Solvers are immutable dataclasses with ``init``, ``step`` and ``terminate`` (optimistix
style); `iterate` owns the `lax.while_loop`.  A solver sees the physics only through an
`EquilibriumSystem`, whose functions have the form ``fn(y, args)``.
"""
from __future__ import annotations

import dataclasses
import enum
import functools
import math
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import progress
from ..vmap_control import batch_sum, branches, each_active
from ..errors import ParameterError


class RESULTS(enum.IntEnum):
    """Why a solve stopped."""

    successful = 0
    max_steps_reached = 1
    nonfinite = 2
    stretch_limit = 3
    neighbour_overflow = 4
    stagnation = 5
    # 6 and 7 were valve state checks; they are `jaxvalve.valve.STATE_FAILURES` now
    escaped = 8            # a node moved farther than the structure's size from the start
    inconsistent = 9       # the loop said converged; an independent evaluation disagrees
    unstable = 10          # converged to an equilibrium that is not stable

    @property
    def message(self):
        return _MESSAGES[self]


_MESSAGES = {
    RESULTS.successful: "converged",
    RESULTS.max_steps_reached: "the iteration limit was reached before convergence",
    RESULTS.nonfinite: "the state or the forces became non-finite (NaN or inf)",
    RESULTS.stretch_limit: "a triangle passed the material's stretch limit (Gent) or collapsed",
    RESULTS.neighbour_overflow: "the contact pair list overflowed its capacity",
    RESULTS.stagnation: ("the solver stagnated: the residual stopped falling (Newton: no "
                         "step reduced it, or its best did not halve within its patience; "
                         "FIRE: its best did not halve within its patience)"),
    RESULTS.escaped: ("a node moved farther from its start than the structure's diameter: "
                      "no equilibrium near the start (a load past the structure's limit "
                      "point, or an unrestrained rigid-body drift)"),
    RESULTS.inconsistent: ("the solver's compiled loop reported convergence, but an "
                           "independent evaluation of its result disagrees (residual, stretch "
                           "check or finiteness), also after recompiling: a wrong compiled "
                           "program, not an equilibrium"),
    RESULTS.unstable: ("the solve reached an equilibrium that is not stable (its exact "
                       "Jacobian has an eigenvalue of negative real part), and pushes "
                       "along that mode found no stable one: a state no closing valve "
                       "settles in"),
}


class EquilibriumSystem(NamedTuple):
    """Functions of the state y (N, 3) and args, closed over the static problem.

    force(y, args) -> (N, 3): total force, zero rows at fixed nodes.
    scale(y, args) -> (): force scale for the relative residual (||F_pressure||).
    admissible(y, args) -> bool: all triangles inside the material's stretch limit.
    bound(y, args) -> (N,): per-node stiffness bound (N/mm).
    block_diag(y, args) -> (N, 3, 3): stiffness diagonal blocks (preconditioner).
    update(y, args) -> args: refresh of the contact pair list (identity without contact).
    overflow(args) -> bool: a pair list overflowed.
    laplacian(v, args) -> (N, k): cotangent Laplacian of the reference mesh applied to v.
    free: (N,) bool.
    force_scale(y, args) -> ((N, 3), ()): force and scale from one evaluation (the scale
    at P = 0 set from that force where ``args["f0"]`` is not yet, as `set_f0` does); None:
    `force` and `scale` apart.
    """

    force: Callable
    scale: Callable
    admissible: Callable
    bound: Callable
    block_diag: Callable
    update: Callable
    overflow: Callable
    laplacian: Callable
    free: Any
    force_scale: Callable | None = None


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Stats:
    """steps: outer iterations; force_evals: residual evaluations (incl. line search);
    hvps: Hessian-vector products; residual: final ||F_free|| / ||F_pressure||."""

    steps: Any
    force_evals: Any
    hvps: Any
    residual: Any


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Solution:
    """Equilibrium ``x`` (N, 3) mm, ``result`` (RESULTS code, int array), `Stats`, and the
    contact pair list used at the end (or None)."""

    x: Any
    result: Any
    stats: Stats
    nbrs: Any = None

    @property
    def converged(self):
        return bool(int(self.result) == RESULTS.successful)

    @property
    def status(self) -> str:
        """The name of the outcome: the `RESULTS` name of ``result``."""
        return RESULTS(int(self.result)).name

    def _message(self) -> str:
        return RESULTS(int(self.result)).message

    def describe(self):
        return (f"{self.status}: {self._message()} (steps={int(self.stats.steps)}, "
                f"relative residual={float(self.stats.residual):.3e})")


#: The ranges `check_settings` knows: name -> (test, the range in words).
_RANGES = {
    "positive": (lambda v: _real(v) and v > 0, "finite and > 0"),
    "unit": (lambda v: _real(v) and 0 < v < 1, "in (0, 1)"),
    "unit_closed": (lambda v: _real(v) and 0 < v <= 1, "in (0, 1]"),
    "above_one": (lambda v: _real(v) and v > 1, "finite and > 1"),
    "count": (lambda v: _integer(v) and v >= 0, "an integer >= 0"),
    "positive_count": (lambda v: _integer(v) and v > 0, "an integer >= 1"),
}


def _real(v):
    """A finite real Python or NumPy scalar (not a bool, not an array: no JAX call, so
    making a solver never starts the backend)."""
    return (isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool)
            and math.isfinite(v))


def _integer(v):
    return isinstance(v, (int, np.integer)) and not isinstance(v, bool)


def check_settings(solver, ranges: dict, optional: tuple = ()):
    """Raise `ParameterError` naming the first setting of ``solver`` outside its range.

    ranges: {field name: a key of `_RANGES`}; optional: fields that may also be None.
    Called by each solver's ``__post_init__``, so a bad setting fails when the solver is
    made, before anything is traced or compiled."""
    cls = type(solver).__name__
    for name, kind in ranges.items():
        v = getattr(solver, name)
        if v is None and name in optional:
            continue
        test, words = _RANGES[kind]
        if not test(v):
            extra = " (or None)" if name in optional else ""
            raise ParameterError(f"{cls}.{name} must be {words}{extra}; got {v!r}")


def relative_residual(system, y, args, F=None):
    F = system.force(y, args) if F is None else F
    s = system.scale(y, args)
    return jnp.linalg.norm(F) / jnp.where(s > 0, s, 1.0)


def escape_distance(x0):
    """The diameter of the state x0 (N, 3) mm (twice its largest distance from the
    centroid): the farthest any node may move in one solve (`RESULTS.escaped`).  An
    equilibrium near x0 lies within it; a structure that passes it is running away."""
    c = jnp.mean(x0, axis=0)
    return 2.0 * jnp.max(jnp.linalg.norm(x0 - c, axis=-1))


def escaped(y, x0, distance):
    """True where a node of y (N, 3) moved farther than ``distance`` mm from x0."""
    return jnp.max(jnp.sum((y - x0) ** 2, axis=-1)) > distance**2


def check_state(system, y, args, F, admissible=None):
    """RESULTS code for an invalid state (nonfinite / stretch limit / overflow / escaped),
    else -1.  ``args`` holds the solve's start ``x_start`` and ``escape`` distance (mm).
    admissible: ``system.admissible(y, args)`` where the solver has it already."""
    finite = jnp.all(jnp.isfinite(y)) & jnp.all(jnp.isfinite(F))
    code = jnp.where(~finite, RESULTS.nonfinite, -1)
    admissible = system.admissible(y, args) if admissible is None else admissible
    code = jnp.where((code < 0) & ~admissible, RESULTS.stretch_limit, code)
    code = jnp.where((code < 0) & escaped(y, args["x_start"], args["escape"]),
                     RESULTS.escaped, code)
    code = jnp.where((code < 0) & system.overflow(args), RESULTS.neighbour_overflow, code)
    return code


def force_and_scale(system, y, args):
    """(F, scale) at y: `EquilibriumSystem.force_scale`, or `force` and `scale` apart
    (with ``args["f0"]`` set from F, `set_f0`)."""
    if system.force_scale is not None:
        return system.force_scale(y, args)
    F = system.force(y, args)
    return F, system.scale(y, set_f0(args, F) if "f0" in args else args)


def set_f0(args, F0):
    """Set the residual scale at P = 0 (``args["f0"]``, sentinel < 0) from a first force
    (a no-op once set: the loop calls it after each step of a lazy-force solver, and FIRE
    before it measures its residual in the step)."""
    f0 = jnp.linalg.norm(F0)
    return dict(args, f0=jnp.where(args["f0"] < 0, jnp.where(f0 > 0, f0, 1.0), args["f0"]))


#: the entries of ``args`` a loop step may change (`EquilibriumSystem.update`, `set_f0`)
_STEP_ARGS = ("nbrs", "f0")


def _send_beacon(solver, system, y, args, state, n):
    """Every `progress.BEACON_EVERY` steps: the step count and the relative residual to
    the host (`jaxvalve.progress.beacon`)."""
    name = type(solver).__name__

    def send():
        r = (relative_residual(system, y, args, state["F"]) if "F" in state
             else jnp.asarray(jnp.nan, y.dtype))
        jax.debug.callback(functools.partial(progress.beacon, solver=name), n, r)

    jax.lax.cond(n % progress.BEACON_EVERY == 0, send, lambda: None)


def iterate(solver, system, y0, args, *, members_apart: bool = False, handoff: int = 0,
            beacon: bool = True):
    """Run ``solver`` from y0 in one `lax.while_loop`.  Returns (y, args, state, result, n).
    ``args`` must be current for y0 (its pair list built or updated there).

    Under `jax.vmap` (`jaxvalve.batch`) the loop runs until every member has finished, and
    a finished member's state is kept.  By default the steps of all members are one
    vectorised program.  members_apart: each member runs its own loop, one member after
    the other (`vmap_control.each_active`): the same compiled loop as a single solve, so a
    member's result is that of a single solve to the last bit, and a finished member costs
    nothing.  handoff (vectorised steps only): once at most ``handoff`` members are still
    running, each of them finishes in its own loop, so that a straggler's last steps cost
    what they cost alone, not a whole batch's vectorised step (0: never).  Unbatched, all
    of these give the single solve.  beacon: send the loop's progress to the host
    (`jaxvalve.progress`) through `jax.debug.callback`; a batched loop must pass False
    (under vmap the call would run at every step).  A program with the callback is not
    kept by the persistent compilation cache: a solve from the host runs the loop in
    stretches instead (`loop_start`, `loop_chunk`, `loop_end`)."""
    c = loop_start(solver, system, y0, args)
    # The args other than the pair list and f0 are loop constants: carried only where the
    # loop is the single solve's (or a plain vmap of it)
    apart = members_apart or handoff > 0
    args = c[1]
    fixed = {k: v for k, v in args.items() if k not in _STEP_ARGS} if apart else {}
    strip = lambda a: {k: v for k, v in a.items() if k not in fixed}
    running = _running(solver)
    stepper = lambda send: _stepper(solver, system, fixed, send)
    trip = stepper(beacon)

    def member_loop(*c):
        # one member's own loop (`each_active`): unbatched, so it reports its progress and,
        # at its end, that one more member has finished
        c = jax.lax.while_loop(running, stepper(True), c)
        jax.debug.callback(progress.member_done)
        return c

    def trip_kept(c):
        # `trip` for a loop whose predicate is one for the batch: a member that has stopped
        # keeps its carry (what vmap's own select does in the plain vectorised loop)
        live = running(c)
        return jax.tree_util.tree_map(lambda p, q: jnp.where(live, p, q), trip(c), c)

    c = (c[0], strip(args), *c[2:])
    if not apart:
        c = jax.lax.while_loop(running, trip, c)
    else:
        if not members_apart:
            # vectorised while more than ``handoff`` members run, the rebuilds too as one
            # array program (`vmap_control.branches("select")`)
            many = lambda c: batch_sum(running(c).astype(jnp.int32)) > handoff
            with branches("select"):
                c = jax.lax.while_loop(many, trip_kept, c)
        # then each member still running finishes in its own loop, the single solve's
        c = each_active(running(c), member_loop, *c)
    y, args, state, n, done, result, y_upd = c
    return loop_end((y, {**fixed, **args}, state, n, done, result, y_upd))


def loop_start(solver, system, y0, args):
    """The carry of `iterate`'s loop at y0: (y, args, state, n, done, result, y_upd),
    with the solver's state and the residual scale at P = 0 (``f0``) set."""
    state = solver.init(system, y0, args)
    lazy = getattr(solver, "lazy_force", False)   # F(y0) comes from the first step
    if "f0" in args and not lazy:  # residual scale at P = 0: the initial force
        F0 = state["F"] if "F" in state else system.force(y0, args)
        args = set_f0(args, F0)
    done, result = solver.terminate(system, y0, args, state)
    return (y0, args, state, jnp.asarray(0), done, result, y0)


def loop_chunk(solver, system, c, stop):
    """The single solve's loop from the carry c (`loop_start`) until it is done, at its
    step cap or at ``stop`` steps (traced), without beacons: the host calls it once per
    `progress.BEACON_EVERY` steps and sends the beacon itself (`loop_residual`), so that
    the compiled program holds no host callback and the persistent compilation cache
    keeps it."""
    running = _running(solver)
    return jax.lax.while_loop(lambda c: running(c) & (c[3] < stop),
                              _stepper(solver, system, {}, False), c)


def loop_running(solver, c):
    """Whether the loop of carry c has steps left (not done, under the step cap)."""
    return _running(solver)(c)


def loop_residual(system, c):
    """The relative residual of carry c, as a beacon reports it (nan before a force)."""
    y, args, state = c[0], c[1], c[2]
    return (relative_residual(system, y, args, state["F"]) if "F" in state
            else jnp.asarray(jnp.nan, y.dtype))


def loop_end(c):
    """(y, args, state, result, n) of a finished carry: an unfinished loop is at its cap."""
    y, args, state, n, done, result, _ = c
    result = jnp.where(done, result, RESULTS.max_steps_reached)
    return y, args, state, result, n


def _running(solver):
    def running(c):
        _, _, _, n, done, _, _ = c
        return (~done) & (n < solver.max_steps)
    return running


def _stepper(solver, system, fixed, send):
    """One step of `iterate`'s loop on its carry; ``fixed``: the args held out of the
    carry (members apart); ``send``: a beacon every `progress.BEACON_EVERY` steps."""
    lazy = getattr(solver, "lazy_force", False)

    def update(y, args, done, y_upd):
        # A vectorised batch also steps the members that have finished (and vmap discards
        # the result).  Such a member updates its pair list at the state of its last update
        # (a no-op: nothing is rebuilt), and the solver sees ``active`` False (FIRE then
        # refreshes no masses).  In a single solve, done is False here and y_upd is y.
        y_upd = jnp.where(~done, y, y_upd)
        return system.update(y_upd, args), y_upd

    def advance(y, args, state, done):
        y, state = solver.step(system, y, dict(args, active=~done), state)
        if "f0" in args and lazy:
            args = set_f0(args, state["F"])
        done, result = solver.terminate(system, y, args, state)
        return y, args, state, done, result

    def trip(c):
        # one step: the single solve's loop body (under a plain vmap, every member's)
        y, args, state, n, done, result, y_upd = c
        a, y_upd = update(y, {**fixed, **args}, done, y_upd)
        y, a, state, done, result = advance(y, a, state, done)
        if send:
            _send_beacon(solver, system, y, a, state, n + 1)
        return y, {k: v for k, v in a.items() if k not in fixed}, state, n + 1, done, result, y_upd
    return trip
