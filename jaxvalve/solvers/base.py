"""Result codes, the solution record, the equilibrium system and the one driver loop.

Solvers are immutable dataclasses with ``init``, ``step`` and ``terminate`` (optimistix
style); `start`, `run` and `end` own the `lax.while_loop` (`iterate` is the three in one).
A solver sees the physics only through an `EquilibriumSystem`, whose functions have the
form ``fn(y, args)``.
"""
from __future__ import annotations

import dataclasses
import enum
import math
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

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
    RESULTS.unstable: ("the solve reached an equilibrium that is not stable (its exact "
                       "Jacobian has an eigenvalue of negative real part), and pushes "
                       "along that mode found no stable one: a state no closing valve "
                       "settles in"),
}


class EquilibriumSystem(NamedTuple):
    """Functions of the state y (N, 3) and args, closed over the static problem.

    force(y, args) -> (N, 3): total force, zero rows at fixed nodes.
    scale(y, args) -> (): force scale for the relative residual (||F_pressure||).
    parts(y, args) -> (force (N, 3), scale (), nearest contact distance per node (N,) mm,
    contact stiffness per node (N,) N/mm) from one evaluation (+inf and 0 without
    barrier contact).
    admissible(y, args) -> bool: all triangles inside the material's stretch limit.
    bound(y, args) -> (N,): per-node stiffness bound (N/mm) of the membrane.
    block_diag(y, args) -> (N, 3, 3): stiffness diagonal blocks (preconditioner).
    update(y, args) -> args: the contact pair lists brought up to date at y.
    overflow(args) -> bool: a pair list overflowed.
    step_cap(y, args) -> (): the largest node move (mm) a step from y may take with the
    pair lists of args (+inf without contact).
    laplacian(v, args) -> (N, k): cotangent Laplacian of the reference mesh applied to v.
    free: (N,) bool.
    """

    force: Callable
    scale: Callable
    parts: Callable
    admissible: Callable
    bound: Callable
    block_diag: Callable
    update: Callable
    overflow: Callable
    step_cap: Callable
    laplacian: Callable
    free: Any


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
    """Equilibrium ``x`` (N, 3) mm, ``result`` (RESULTS code, int array), `Stats`, and,
    with contact, the pair ``lists`` at the end, their capacities ``caps`` and ``topo``
    (`jaxvalve.contact.pairs`), for the adjoint and the next solve.  ``newton_steps``: the
    steps of the engine's Newton finish (0: none ran)."""

    x: Any
    result: Any
    stats: Stats
    lists: Any = None
    caps: Any = dataclasses.field(default=None, metadata=dict(static=True))
    topo: Any = None
    newton_steps: int = dataclasses.field(default=0, metadata=dict(static=True))

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


def set_f0(args, F0):
    """Set the residual scale at P = 0 (``args["f0"]``, sentinel < 0) from a first force
    (a no-op once set)."""
    f0 = jnp.linalg.norm(F0)
    return dict(args, f0=jnp.where(args["f0"] < 0, jnp.where(f0 > 0, f0, 1.0), args["f0"]))


class Carry(NamedTuple):
    """The loop's carry: state y, args, the solver's state, step count n, done, result."""

    y: Any
    args: Any
    state: Any
    n: Any
    done: Any
    result: Any


def start(solver, system, y0, args) -> Carry:
    """The carry at y0.  A solver whose first step evaluates F(y0) (``lazy_force``:
    FIRE's null step 0, which also brings the pair lists up to date) needs no force here,
    nor the residual scale at rest (``args["f0"]``); the others get both, with the pair
    lists brought up to date at y0."""
    if getattr(solver, "lazy_force", False):
        state = solver.init(system, y0, args)
        return Carry(y0, args, state, jnp.asarray(0, jnp.int32), jnp.asarray(False),
                     jnp.asarray(int(RESULTS.successful)))
    args = system.update(y0, args)
    state = solver.init(system, y0, args)
    if "f0" in args and not getattr(solver, "lazy_force", False):
        args = set_f0(args, state["F"] if "F" in state else system.force(y0, args))
    done, result = solver.terminate(system, y0, args, state)
    return Carry(y0, args, state, jnp.asarray(0, jnp.int32), done, result)


def running(solver, c: Carry):
    """Whether the loop of carry c has steps left (not done, under the step cap)."""
    return (~c.done) & (c.n < solver.max_steps)


def run(solver, system, c: Carry, stop=None) -> Carry:
    """The loop from carry c until it is done, at its step cap, or at ``stop`` steps (a
    traced count: a host-driven solve runs its loop in stretches between progress
    reports; inside a trace the whole loop is one).  A solver's step brings the pair
    lists up to date itself, before it evaluates a force."""
    lazy = getattr(solver, "lazy_force", False)

    def cond(c):
        ok = running(solver, c)
        return ok if stop is None else ok & (c.n < stop)

    def body(c):
        y, args, state = solver.step(system, c.y, c.args, c.state)
        if "f0" in args and lazy:
            args = set_f0(args, state["F"])
        done, result = solver.terminate(system, y, args, state)
        return Carry(y, args, state, c.n + 1, done, result)

    return jax.lax.while_loop(cond, body, c)


def end(c: Carry):
    """(y, args, state, result, n) of a finished carry: an unfinished loop is at its cap."""
    return c.y, c.args, c.state, jnp.where(c.done, c.result, RESULTS.max_steps_reached), c.n


def iterate(solver, system, y0, args):
    """``solver`` from y0 in one `lax.while_loop`: (y, args, state, result, n)."""
    return end(run(solver, system, start(solver, system, y0, args)))
