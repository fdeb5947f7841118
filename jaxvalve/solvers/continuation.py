"""Continuation in pressure, and the limit point where it ends.

A membrane without strain stiffening (linear springs, neo-Hookean) has an inflation limit:
a spherical neo-Hookean balloon of radius R and thickness H is in equilibrium only below
P_max = 2 mu H / R (7^(-1/6) - 7^(-7/6)) ~ 1.24 mu H / R (at the stretch 7^(1/6)); above it
there is no equilibrium and the membrane inflates without end.  A solve there ends with
`RESULTS.escaped` (a node moved farther than the structure's diameter from its start).

`ramp` closes the gap between the highest pressure with an equilibrium and a target:
from the start state it tries the target; where a solve runs away it bisects the
pressure interval between the last equilibrium and the runaway, warm-starting every solve
from the last equilibrium, until the interval is narrower than ``rtol`` times its upper
end.  A solve that stagnates (a Newton line search that finds no acceptable step: the
load increment was too large for the solver, not a sign that no equilibrium exists), or
fails in another way its solver declares (`cut_on`: the engine's step cap and
stagnation), is treated as a step too long: the ramp retries at the midpoint between the last
equilibrium and the stalled pressure, and after each equilibrium reached that way tries
the stalled pressure again, from the nearer state (under a runaway, a pressure that
has stalled twice bounds the bracket like a runaway, and is solved again only from an
equilibrium within ``rtol`` of it).  The result is one of

* ``converged``: the target pressure has an equilibrium (the usual case, one solve);
* ``limit_point``: at least one solve converged, every solve above ``pressure`` ran away
  and every one at or below it converged, within the bracket ``(pressure, p_escape)``:
  no equilibrium at the target connected to the start, the highest one found being the
  state ``x`` at ``pressure`` (a start that is not itself an equilibrium is never
  reported as a limit point: with no converged solve the ramp ends as ``escaped``).
  Also where solves above a runaway's bracket stall (a failure in ``cut``) within
  ``rtol`` of the highest equilibrium: just past a fold the state drifts slowly away
  through the ghost of the lost equilibrium, and a solve there ends at its step cap
  before it has moved far enough to count as a runaway; ``p_stall`` is then the lowest
  stalled pressure;
* any other `RESULTS` name: a solve failed for another reason (step cap, crossing
  leaflets ...), or stagnated within ``rtol`` of the last equilibrium, or failed after the
  ramp's step budget was spent (`Ramp.max_steps`), which ends the ramp and is reported as
  it is, never as a limit point.  Once a solve has run away the budget no longer applies:
  the ramp then only narrows a bracket under the runaway, each solve halving it or
  raising its lower end, for at most ``max_solves`` solves.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable

import numpy as np

from ..errors import ParameterError
from .base import RESULTS
from .base import check_settings

__all__ = ["Ramp", "RampResult", "ramp", "cut_on", "CUT_ON"]


@dataclasses.dataclass(frozen=True)
class Ramp:
    """Settings of `ramp`: rtol, the bracket width (relative to its upper pressure) at which
    a limit point is declared; max_solves, the most equilibrium solves in one ramp;
    max_steps, the most solver steps over all of them (None: no bound but max_solves),
    checked after each failed solve until a solve has run away, so that a ramp that cannot
    converge ends in bounded time."""

    rtol: float = 0.01
    max_solves: int = 30
    max_steps: int | None = None

    def __post_init__(self):
        check_settings(self, dict(rtol="unit", max_solves="positive_count",
                                  max_steps="positive_count"), optional=("max_steps",))

    @classmethod
    def for_solver(cls, solver, solves_worth: int = 10):
        """The defaults, with a budget of ``solves_worth`` full solves of ``solver``'s
        steps (its ``max_steps``) where it has a cap, so that a ramp that cannot converge
        ends in bounded time."""
        cap = getattr(solver, "max_steps", None)
        return cls(max_steps=None if cap is None else solves_worth * int(cap))


@dataclasses.dataclass(frozen=True)
class RampResult:
    """Outcome of `ramp`.

    status: 'converged', 'limit_point', or the `RESULTS` name of the failure that ended it.
    pressure: the highest pressure with a converged equilibrium (the target when
    converged; the start pressure when none converged).  p_escape: the lowest pressure at
    which a solve ran away (None when none did).  x (N, 3): the state at ``pressure``.
    solution: the solve that gave x (None when it is the start state), failure: the solve
    that ended the ramp (None when converged).  history: (pressure, result name, steps,
    relative residual) per solve.  steps: solver steps over all solves.  p_stall: for a
    limit point whose nearest failures stalled rather than ran away, the lowest stalled
    pressure above ``pressure`` (else None)."""

    status: str
    pressure: float
    p_escape: float | None
    x: Any
    solution: Any
    failure: Any
    history: tuple
    steps: int
    p_stall: float | None = None

    @property
    def converged(self) -> bool:
        return self.status == "converged"

    @property
    def limit_point(self) -> bool:
        return self.status == "limit_point"

    @property
    def final(self):
        """(`Solution`, pressure) of the state the ramp reports: the equilibrium at
        ``pressure`` where it ended by converging, at a limit point or in runaways after
        an equilibrium; otherwise the solve that failed, at its pressure."""
        if self.solution is not None and self.status in ("converged", "limit_point",
                                                         "escaped"):
            return self.solution, self.pressure
        return self.failure, self.history[-1][0]

    def describe(self) -> str:
        if self.status == "converged":
            return f"converged at {self.pressure:g}"
        if self.status == "limit_point":
            stalled = ("" if self.p_stall is None
                       else f"solves from {self.p_stall:.4g} stalled, ")
            return (f"limit_point: no equilibrium above {self.pressure:.4g} ({stalled}solves "
                    f"at {self.p_escape:.4g} and above ran away); the state shown is the "
                    f"equilibrium at {self.pressure:.4g}")
        f = self.failure
        tail = f": {f.describe()}" if f is not None else ""
        return f"{self.status} (highest equilibrium at {self.pressure:.4g}){tail}"


#: The failures after which `ramp` cuts the load step, by default: a stagnated Newton
#: line search.
CUT_ON = ("stagnation",)


def cut_on(solver) -> tuple:
    """The `RESULTS` names after which `ramp` cuts the load step for ``solver``: its own
    ``cut_on`` where it declares one (a Newton solver that has not converged within its
    iteration cap is, as in finite-element load stepping, taken to have been given too
    long a step), else `CUT_ON`."""
    return tuple(getattr(solver, "cut_on", CUT_ON))


def ramp(solve: Callable, x0, p_target: float, p_start: float = 0.0,
         settings: Ramp | None = None, cut: tuple = CUT_ON) -> RampResult:
    """Continuation in pressure from an equilibrium x0 at p_start to p_target.

    solve(p, x) -> `Solution`: the equilibrium at pressure p from the start x.  The first
    solve is at p_target; where it converges or fails for a reason other than a runaway
    or a failure in ``cut``, it is the only one.  Pressures in any unit, p_target >
    p_start >= 0.  cut: the `RESULTS` names of failures that cut the load step
    (`cut_on`)."""
    settings = Ramp() if settings is None else settings
    p_target, p_start = float(p_target), float(p_start)
    if not (np.isfinite(p_target) and np.isfinite(p_start) and p_target > p_start >= 0):
        raise ParameterError(f"ramp needs p_target > p_start >= 0; got p_start={p_start}, "
                             f"p_target={p_target}")
    p_ok, x_ok, sol_ok = p_start, x0, None
    p_bad = None      # the lowest pressure at which a solve ran away
    sol_bad = None    # that solve
    p_stall = None    # the pressure of the last stagnated solve not yet passed
    n_stall = 0       # how many solves at p_stall have stalled
    history, steps = [], 0
    sol_fail = None   # the last failed solve
    p = p_target
    for _ in range(settings.max_solves):
        sol = solve(p, x_ok)
        status = sol.status
        n = int(sol.stats.steps)
        steps += n
        history.append((p, status, n, float(sol.stats.residual)))
        if sol.converged:
            p_ok, x_ok, sol_ok = p, sol.x, sol
            if p >= p_target:
                return RampResult("converged", p, p_bad, x_ok, sol_ok, None, tuple(history),
                                  steps)
            if p_stall is not None and p >= p_stall:
                p_stall = None
            if (p_bad is not None and (p_stall is None or p_stall >= p_bad)
                    and p_bad - p_ok <= settings.rtol * p_bad):
                # the bracket under the runaway closed from below
                return RampResult("limit_point", p_ok, p_bad, x_ok, sol_ok, sol_bad,
                                  tuple(history), steps)
        elif status == RESULTS.escaped.name:
            p_bad, sol_bad = p, sol
            if p_bad - p_ok <= settings.rtol * p_bad:
                if sol_ok is None:           # runaway down to the start: no equilibrium
                    break
                return RampResult("limit_point", p_ok, p_bad, x_ok, sol_ok, sol,
                                  tuple(history), steps)
        elif status in cut and p - p_ok > settings.rtol * p:
            n_stall = n_stall + 1 if p == p_stall else 1
            p_stall = p
        elif status in cut and p_bad is not None and sol_ok is not None and p < p_bad:
            # stalled within rtol of an equilibrium, under a runaway: past the fold
            return RampResult("limit_point", p_ok, p_bad, x_ok, sol_ok, sol,
                              tuple(history), steps, p_stall=p)
        else:
            return RampResult(status, p_ok, p_bad, x_ok, sol_ok, sol, tuple(history), steps)
        if not sol.converged and p_bad is None and _spent(settings, steps):  # budget spent
            return RampResult(status, p_ok, p_bad, x_ok, sol_ok, sol, tuple(history), steps)
        if not sol.converged:
            sol_fail = sol
        p = _next_pressure(p_ok, p_bad, p_stall, p_target, sol.converged, settings.rtol,
                           n_stall)
    # out of solves (or a runaway down to the start): the last solve's failure, a runaway
    # or a stagnation (a converged solve at the target returns above); out of solves just
    # after an equilibrium (which a failure must have preceded): the last failure
    last = sol_fail if sol.converged else sol
    return RampResult(last.status, p_ok, p_bad, x_ok, sol_ok, last, tuple(history), steps)


def _spent(settings: Ramp, steps: int) -> bool:
    """Whether ``steps`` solver steps spend the ramp's step budget."""
    return settings.max_steps is not None and steps >= settings.max_steps


def _next_pressure(p_ok, p_bad, p_stall, p_target, converged, rtol, n_stall):
    """The next pressure of `ramp`: the midpoint below the lowest runaway or stall; after
    an equilibrium below a stall, the stalled pressure itself (from the nearer state),
    except under a runaway once that pressure has stalled twice (``n_stall``): then it
    bounds the bracket like the runaway, the ramp takes the midpoint below it and solves
    it again only from an equilibrium within ``rtol`` of it (where it stalls again at a
    fold, which ends the ramp, or converges and the bracket moves up); else the target.

    A stall under a runaway far from the fold is often a load step too long, and one
    retry from the nearer state passes it (the springs at 0.1 MPa, template (a), h = 2
    mm: 41.5 mmHg stalled from 3 under the runaway at 80 and converged from 22.2; made a
    bracket end at once, the ramp crept up to it through six more equilibria).  Near the
    fold every retry is a full solve to the Newton step cap (the same valve: the stall
    at 46.3 mmHg was retried from 43.9, 45.1, 45.7 and 46.0 mmHg)."""
    if p_stall is not None and converged:
        if p_bad is None:
            return p_stall
        if n_stall < 2 or p_stall >= p_bad:
            return min(p_stall, 0.5 * (p_ok + p_bad))
        return p_stall if p_stall - p_ok <= rtol * p_stall else 0.5 * (p_ok + p_stall)
    failed = [q for q in (p_bad, p_stall) if q is not None]
    return 0.5 * (p_ok + min(failed)) if failed else p_target
