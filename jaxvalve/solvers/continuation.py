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
fails in another way its solver declares (`cut_on`: the barrier Newton's iteration cap),
is treated as a step too long: the ramp retries at the midpoint between the last
equilibrium and the stalled pressure, and after each equilibrium reached that way tries
the stalled pressure again, from the nearer state (under a runaway, a pressure that
has stalled twice bounds the bracket like a runaway, and is solved again only from an
equilibrium within ``rtol`` of it).  Under a runaway a full solve is stopped, as a
stall, after a few times as many steps as the slowest converged solve of the ramp took
(`Ramp.stall_factor`, `_bracket_cap`): near the fold a solve converges in a few steps or
drifts to any cap.
(The soft Table 4 cell E1 = 0.05, E2 = 0.569 MPa stagnates from 3 straight to 80
mmHg on the barrier path and converges through 10, 20 and 40 mmHg.)  The result is one of

* ``converged``: the target pressure has an equilibrium (the usual case, one solve);
* ``limit_point``: at least one solve converged, every solve above ``pressure`` ran away
  and every one at or below it converged, within the bracket ``(pressure, p_escape)``:
  no equilibrium at the target connected to the start, the highest one found being the
  state ``x`` at ``pressure`` (a start that is not itself an equilibrium is never
  reported as a limit point: with no converged solve the ramp ends as ``escaped``).
  Also where solves above a runaway's bracket stall (a failure in ``cut``) within
  ``rtol`` of the highest equilibrium: just past a fold the state drifts slowly away
  through the ghost of the lost equilibrium, and a Newton solve there ends at its step
  cap before it has moved far enough to count as a runaway (the soft neo-Hookean valve of
  the paper's Table 5, E = 0.1 MPa at h = 1.5 mm: equilibria up to 20.1 mmHg, step caps
  at 20.3-21.0, runaways from 22.2); ``p_stall`` is then the lowest stalled pressure;
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

__all__ = ["Ramp", "RampResult", "ramp", "cut_on", "CUT_ON", "full_solver"]


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
    #: under a runaway, a full solve (``confirm``) is stopped once it has taken
    #: max(stall_floor, stall_factor x the most steps any converged solve of this ramp
    #: took) without converging, and counts as a stall (`_bracket_cap`)
    stall_factor: float = 3.0
    stall_floor: int = 40

    def __post_init__(self):
        check_settings(self, dict(rtol="unit", max_solves="positive_count",
                                  max_steps="positive_count", stall_factor="positive",
                                  stall_floor="positive_count"), optional=("max_steps",))

    @classmethod
    def for_solver(cls, solver, solves_worth: int = 10):
        """The defaults, with a budget of ``solves_worth`` full solves of ``solver``'s
        steps (its ``max_steps``) where it has a cap.  Without it a barrier ramp that could
        not converge (Table 4 cell E1 = 0.106, E2 = 0.3 MPa) ran for more than 25 minutes:
        30 solves of up to 200 Newton steps."""
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


def full_solver(solver):
    """``solver`` without its early stop, where it declares one (``without_patience``: the
    barrier Newton's patience), else None: the solver of `ramp`'s ``confirm`` solves."""
    without = getattr(solver, "without_patience", None)
    return None if without is None else without()


def ramp(solve: Callable, x0, p_target: float, p_start: float = 0.0,
         settings: Ramp | None = None, cut: tuple = CUT_ON,
         confirm: Callable | None = None, hint: float | None = None) -> RampResult:
    """Continuation in pressure from an equilibrium x0 at p_start to p_target.

    solve(p, x) -> `Solution`: the equilibrium at pressure p from the start x.  The first
    solve is at p_target; where it converges or fails for a reason other than a runaway,
    it is the only one.  Pressures in any unit, p_target > p_start >= 0.
    cut: the `RESULTS` names of failures that cut the load step (`cut_on`).
    confirm(p, x, max_steps) -> `Solution`: where ``solve`` stops early (a solver's
    patience), the same solve without that stop, stopped at ``max_steps`` steps (None:
    the solver's own cap; under a runaway, `_bracket_cap`).  Before the ramp ends on a
    failure in ``cut`` (within ``rtol`` of the highest equilibrium, or with its step
    budget spent) with no runaway seen, it solves once more from the highest equilibrium
    straight to the target with ``confirm``, and goes on from that solve's outcome: a
    solve stopped for not converging fast enough may have been a runaway that had not
    yet gone far enough to count as one (without its drift guard, the barrier Newton's
    patience stopped the runaways past the 0.1 MPa springs' limit point after 62-74
    steps), or may have been about to converge.  Once a solve has run away every solve
    is ``confirm``'s: the ramp then brackets a limit point, where Newton
    converges slowly, and early stops near the fold placed the limit too low (those
    springs at h = 0.88 mm: 35.4 mmHg against 37.3 without the early stop).
    hint: a pressure at which another solver ran away on the same valve (the failed
    path's lowest runaway, `jaxvalve.valve.closure.fall_back`).  After the first runaway
    here the ramp tries it next, where it lies inside the bracket, instead of the
    midpoint: a runaway there bounds the bracket as any other, an equilibrium there
    raises its lower end.  Nothing is taken on trust: only this ramp's own solves place
    the limit."""
    settings = Ramp() if settings is None else settings
    slowest = 0       # the most steps a converged solve of this ramp took
    p_target, p_start = float(p_target), float(p_start)
    if not (np.isfinite(p_target) and np.isfinite(p_start) and p_target > p_start >= 0):
        raise ParameterError(f"ramp needs p_target > p_start >= 0; got p_start={p_start}, "
                             f"p_target={p_target}")
    if hint is not None and not (np.isfinite(hint) and hint > 0):
        raise ParameterError(f"ramp's hint must be a positive finite pressure; got {hint}")
    p_ok, x_ok, sol_ok = p_start, x0, None
    p_bad = None      # the lowest pressure at which a solve ran away
    sol_bad = None    # that solve
    p_stall = None    # the pressure of the last stagnated solve not yet passed
    n_stall = 0       # how many solves at p_stall have stalled
    history, steps = [], 0
    sol_fail = None   # the last failed solve
    p = p_target
    confirmed = confirm is None   # the one full solve to the target, done or not needed
    to_target = False             # this solve is that one
    for _ in range(settings.max_solves):
        # once a solve has run away, every solve is a full one: the ramp then brackets
        # a limit point, where Newton converges slowly and an early stop near the fold
        # would place the limit too low
        full = confirm is not None and (to_target or p_bad is not None)
        if full:
            cap = None if p_bad is None else _bracket_cap(settings, slowest)
            sol = confirm(p, x_ok, max_steps=cap)
        else:
            sol = solve(p, x_ok)
        was_target, to_target = to_target, False
        status = sol.status
        n = int(sol.stats.steps)
        steps += n
        history.append((p, status, n, float(sol.stats.residual)))
        if was_target and not sol.converged and status != RESULTS.escaped.name:
            # the full solve to the target fails as well: that failure ends the ramp
            return RampResult(status, p_ok, p_bad, x_ok, sol_ok, sol, tuple(history), steps)
        if sol.converged:
            p_ok, x_ok, sol_ok = p, sol.x, sol
            slowest = max(slowest, n)
            if p >= p_target:
                return RampResult("converged", p, p_bad, x_ok, sol_ok, None, tuple(history),
                                  steps)
            if p_stall is not None and p >= p_stall:
                p_stall = None
            if (p_bad is not None and (p_stall is None or p_stall >= p_bad)
                    and p_bad - p_ok <= settings.rtol * p_bad):
                # the bracket under the runaway closed from below: every solve under it
                # converged (without this the midpoints crept up to the runaway, each
                # converging, until the ramp ran out of solves and reported the runaway)
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
        elif status in cut and not confirmed:
            confirmed = to_target = True
        else:
            return RampResult(status, p_ok, p_bad, x_ok, sol_ok, sol, tuple(history), steps)
        if not sol.converged and p_bad is None and _spent(settings, steps):  # budget spent
            if status in cut and not confirmed:
                confirmed = to_target = True
            else:
                return RampResult(status, p_ok, p_bad, x_ok, sol_ok, sol, tuple(history),
                                  steps)
        if not sol.converged:
            sol_fail = sol
        # the ramp would end on a failure that may be the early stop's (`confirm`): one
        # solve from the highest equilibrium straight to the target, without it
        p = p_target if to_target else _next_pressure(p_ok, p_bad, p_stall, p_target,
                                                      sol.converged, settings.rtol,
                                                      n_stall)
        if (hint is not None and status == RESULTS.escaped.name and p_stall is None
                and p_ok < hint < p_bad):
            p, hint = float(hint), None      # the other solver's runaway, once
    # out of solves (or a runaway down to the start): the last solve's failure, a runaway
    # or a stagnation (a converged solve at the target returns above); out of solves just
    # after an equilibrium (which a failure must have preceded): the last failure
    last = sol_fail if sol.converged else sol
    return RampResult(last.status, p_ok, p_bad, x_ok, sol_ok, last, tuple(history), steps)


def _bracket_cap(settings: Ramp, slowest: int) -> int | None:
    """The step cap of a full solve under a runaway: ``stall_factor`` times the most steps
    a converged solve of this ramp took, at least ``stall_floor`` (None before any solve
    converged: the solver's own cap).  Such a solve starts from an equilibrium near the
    fold, where Newton converges in a few steps or not at all: past the fold the state
    drifts slowly through the ghost of the lost equilibrium and a solve ran to the
    solver's 200-step cap (the soft neo-Hookean valve of the stress tests, template (a),
    E = 0.05 MPa, h = 2 mm: converged solves in the bracket 5-17 steps, three stalls at
    200 steps each, 600 of the ramp's 921).  A solve stopped here is a stall (the cap is
    in ``cut``) and bounds the bracket as one; a runaway stopped before it escaped is
    such a stall too."""
    if slowest == 0:
        return None
    return max(settings.stall_floor, int(np.ceil(settings.stall_factor * slowest)))


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
