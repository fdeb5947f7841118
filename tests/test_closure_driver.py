"""The one closure driver (`jaxvalve.valve.closure`): every caller's loads, continuation, state
checks and reports go through it.

The driver's logic is tested with a scripted solver in place of `valve.close` (a valve
whose equilibrium exists up to a known pressure, ``P_LIM``, and runs away above it), so
each decision is checked exactly and fast, `simulate`'s report of a limit point among
them.  The stress suite's run of a real valve past its limit point, through the same
driver, is in tests/stress/test_stress_special.py.
"""
import types

import numpy as np
import pytest

from jaxvalve import Scene

from jaxvalve.valve import closure
from jaxvalve import valve as V
from jaxvalve.simulation import build_scene_valve
from jaxvalve.solvers import RESULTS, Stats

#: the driver's own logic, without the fallback (tested below, with `FALLBACK`)
SCENE = Scene(h=3.0, max_steps=100, fallback=False)
FALLBACK = SCENE.replace(fallback=True)
P_LIM = 20.0


@pytest.fixture(scope="module")
def valve():
    return build_scene_valve(SCENE)


class Scripted:
    """`valve.close` stand-in: converges in 7 steps at p <= limit (the state moved by p
    mm along x, so each state names its pressure), runs away above it; logs every call."""

    def __init__(self, limit=P_LIM, nonfinite_at=None):
        self.limit, self.nonfinite_at, self.calls = limit, nonfinite_at, []

    def __call__(self, valve, material, p, *, x0, **kw):
        self.calls.append(float(p))
        x = np.asarray(valve.x_start, float).copy()
        x[:, 0] += p
        code = RESULTS.successful if p <= self.limit else RESULTS.escaped
        if self.nonfinite_at is not None and p == self.nonfinite_at:
            x[0, 0], code = np.nan, RESULTS.nonfinite
        return _sol(x, code, 7)


def _sol(x, code, steps, residual=1e-6):
    return V.ValveSolution(x=x, result=np.asarray(int(code)),
                           stats=Stats(steps=steps, force_evals=0, hvps=0,
                                       residual=residual))


def _stand_in(monkeypatch, cls):
    """A factory of ``cls`` stand-ins for `valve.close`, each installed as it is made."""
    def make(**kw):
        s = cls(**kw)
        monkeypatch.setattr(closure.V, "close", s)
        return s
    return make


@pytest.fixture
def scripted(monkeypatch):
    return _stand_in(monkeypatch, Scripted)


def test_loads_in_turn_each_from_the_state_before(valve, scripted):
    s = scripted(limit=100.0)
    he, closed = closure.close_valve(valve, SCENE)
    assert s.calls == [3.0, 80.0]
    assert he.converged and closed.converged and closed.report.steps == 7
    assert he.report.state_pressure == 3.0 and closed.report.pressure == 80.0
    # the state reported is the solve's (x moved by p), as float64
    assert closed.x.dtype == np.float64
    np.testing.assert_allclose(closed.x[:, 0] - np.asarray(valve.x_start)[:, 0], 80.0)


def test_a_load_past_the_limit_ends_at_a_limit_point_and_the_next_is_skipped(valve,
                                                                           scripted):
    s = scripted(limit=P_LIM)
    loads = closure.close_valve(valve, SCENE, pressures=(3.0, 80.0, 120.0))
    he, lim, skipped = loads
    assert he.converged and not lim.converged and lim.limit_point
    rep = lim.report
    assert rep.result == "limit_point" and P_LIM * 0.99 <= rep.limit_pressure <= P_LIM
    assert rep.state_pressure == rep.limit_pressure and "limit_point" in rep.describe()
    # the state shown is the equilibrium at the limit pressure, and the steps count all
    np.testing.assert_allclose(lim.x[:, 0] - np.asarray(valve.x_start)[:, 0],
                               rep.limit_pressure)
    assert rep.steps == 7 * len(lim.ramp.history) and len(lim.ramp.history) > 3
    # the load above it is not solved: no call at 120 mmHg, 0 steps, same outcome
    assert 120.0 not in s.calls
    assert skipped.report.pressure == 120.0 and skipped.report.steps == 0
    assert skipped.report.result == "limit_point"


def test_simulate_reports_the_drivers_limit_point_with_the_state_at_its_pressure(
        valve, scripted):
    """`simulate` hands the driver's outcome on as it is: past the limit its second
    solve is the driver's `limit_point` with the limit pressure, the state and metrics
    are those of the equilibrium at that pressure, the result is not converged, and with
    throw it raises, naming the limit point.  (The same on a real valve, a soft
    neo-Hookean one past its inflation limit: tests/stress/test_stress_special.py.)"""
    from jaxvalve import simulate
    from jaxvalve.errors import ConvergenceError
    from jaxvalve.simulation import measure
    scripted(limit=P_LIM)
    _, lim = closure.close_valve(valve, SCENE)
    res = simulate(SCENE, valve=valve, throw=False)
    rep = res.solves[1]
    assert rep.result == "limit_point" and not res.converged
    assert rep.limit_pressure == lim.report.limit_pressure
    assert P_LIM * 0.99 <= rep.limit_pressure <= P_LIM
    assert res.solves[0].converged and res.solves[0].pressure == 3.0
    # the state at the limit pressure (x moved by p), and its metrics
    np.testing.assert_allclose(res.x[:, 0] - np.asarray(valve.x_start)[:, 0],
                               rep.limit_pressure)
    m = measure(valve, res.x, SCENE.g_c)
    assert res.metrics.h_cc == pytest.approx(m.h_cc, abs=1e-12)
    with pytest.raises(ConvergenceError, match="limit_point"):
        simulate(SCENE, valve=valve)


class Patient(Scripted):
    """`Scripted` through the barrier Newton's patience: with ``solver.patience`` > 0 a
    solve past the limit stops early (`stagnation`, 40 steps) instead of running away;
    logs (pressure, patience) of every call."""

    def __call__(self, valve, material, p, *, x0, solver=None, **kw):
        sol = super().__call__(valve, material, p, x0=x0, **kw)
        self.calls[-1] = (float(p), solver.patience)
        if int(sol.result) == RESULTS.escaped and solver.patience > 0:
            return _sol(np.asarray(x0, float), RESULTS.stagnation, 40, residual=2e-3)
        return sol


def test_the_barrier_path_confirms_an_early_stop_with_a_full_solve(valve, monkeypatch):
    """On the barrier path the driver gives the continuation the solve without the
    patience as its ``confirm``: the early stops past the limit do not hide it, the full
    solve to the target runs away, and the load ends at the limit point, bracketed by
    full solves; the stops alone would have ended it as `stagnation`."""
    from jaxvalve.solvers import BarrierNewton
    s = _stand_in(monkeypatch, Patient)()
    scene = SCENE.replace(contact="barrier", solver="newton")
    assert isinstance(scene.make_solver(), BarrierNewton) and scene.make_solver().patience
    he, lim = closure.close_valve(valve, scene)
    assert he.converged and lim.limit_point, lim.report.describe()
    assert P_LIM * 0.99 <= lim.report.limit_pressure <= P_LIM
    full = [i for i, (_, patience) in enumerate(s.calls) if patience == 0]
    assert s.calls[full[0]] == (80.0, 0) and full == list(range(full[0], len(s.calls)))
    assert any(q > P_LIM and patience for q, patience in s.calls[:full[0]])


def test_a_given_first_attempt_is_used_and_a_stale_one_is_not(valve, scripted, monkeypatch):
    """`simulate_batch` hands its batched attempts in as ``first``: a converged one is
    taken as it is (no solve); one that ran away is followed by the continuation, and the
    next load's batched attempt, which started from the runaway state, is discarded."""
    s = scripted(limit=100.0)
    x = np.asarray(valve.x_start, float)
    given = (_sol(x + 1.0, RESULTS.successful, 11), _sol(x + 2.0, RESULTS.successful, 13))
    he, closed = closure.close_valve(valve, SCENE, first=given)
    assert s.calls == [] and (he.report.steps, closed.report.steps) == (11, 13)
    np.testing.assert_array_equal(closed.x, x + 2.0)

    # a first attempt that stagnated, by a solver that takes a stagnation for a load step
    # too long (`continuation.cut_on`: the barrier Newton; FIRE does not): the
    # continuation retries at half the increment, then at 3 mmHg itself; the 80 mmHg
    # attempt (solved from the stagnated state) is not taken, 80 mmHg is solved afresh
    # from the new equilibrium
    monkeypatch.setattr(closure, "cut_on", lambda solver: ("stagnation",))
    s = scripted(limit=100.0)
    stale = (_sol(x + 5.0, RESULTS.stagnation, 11), _sol(x + 6.0, RESULTS.successful, 13))
    he, closed = closure.close_valve(valve, SCENE, first=stale)
    assert s.calls == [1.5, 3.0, 80.0]
    assert he.converged and len(he.ramp.history) == 3 and he.report.steps == 11 + 7 + 7
    assert closed.converged and closed.report.steps == 7
    np.testing.assert_allclose(closed.x, x + np.array([80.0, 0, 0]))


def test_a_state_that_is_not_finite_stops_the_loads(valve, scripted):
    s = scripted(limit=100.0, nonfinite_at=3.0)
    he, closed = closure.close_valve(valve, SCENE)
    assert he.report.result == "nonfinite" and not he.converged
    assert s.calls == [3.0] and closed.report.steps == 0 and not closed.converged


def test_throw_raises_at_the_first_load_that_did_not_converge(valve, scripted):
    from jaxvalve.errors import ConvergenceError
    scripted(limit=P_LIM)
    with pytest.raises(ConvergenceError, match="80 mmHg did not converge: limit_point"):
        closure.close_valve(valve, SCENE, throw=True)


# ----------------------------------------------------------------------- the fallback
class TwoLaws:
    """`valve.close` stand-in that knows the contact law: on the smooth law it fails
    (``smooth_fails``, e.g. a step cap) above ``smooth_limit`` mmHg, on the barrier law
    it converges in 5 steps everywhere; logs (law, pressure) of every call."""

    def __init__(self, smooth_limit=20.0, smooth_fails=RESULTS.max_steps_reached,
                 barrier_fails=None):
        self.smooth_limit, self.smooth_fails, self.calls = smooth_limit, smooth_fails, []
        self.barrier_fails = barrier_fails

    def __call__(self, valve, material, p, *, x0, contact=None, **kw):
        law = "barrier" if getattr(contact, "barrier", False) else "smooth"
        self.calls.append((law, float(p)))
        x = np.asarray(x0, float).copy()
        x[:, 0] = np.asarray(valve.x_start, float)[:, 0] + p
        if law == "barrier":
            return _sol(x, self.barrier_fails or RESULTS.successful, 5)
        code = RESULTS.successful if p <= self.smooth_limit else self.smooth_fails
        return _sol(x, code, 9)


@pytest.fixture
def two_laws(monkeypatch):
    return _stand_in(monkeypatch, TwoLaws)


def test_a_failed_smooth_closure_is_closed_again_on_the_barrier_law(valve, two_laws):
    """The smooth law's 80 mmHg closure stops at its step cap: both loads are closed
    again on the barrier law, from the smooth law's 3 mmHg state (no swing-shut), and
    each report names the path and the failure."""
    s = two_laws()
    he, closed = closure.close_valve(valve, FALLBACK)
    assert s.calls == [("smooth", 3.0), ("smooth", 80.0), ("barrier", 3.0), ("barrier", 80.0)]
    for ls in (he, closed):
        assert ls.converged and ls.report.path == "newton+barrier"
        assert ls.report.steps == 5
        assert ls.report.fallback.startswith("fire+smooth failed at 80 mmHg: "
                                             "max_steps_reached")
        assert "newton+barrier, after fire+smooth failed" in ls.report.describe()
    np.testing.assert_allclose(closed.x[:, 0] - np.asarray(valve.x_start)[:, 0], 80.0)


def test_a_failure_at_the_first_load_skips_the_smooth_laws_later_loads(valve, two_laws):
    s = two_laws(smooth_limit=1.0)
    he, closed = closure.close_valve(valve, FALLBACK)
    assert s.calls == [("smooth", 3.0), ("barrier", 3.0), ("barrier", 80.0)]
    assert he.converged and closed.converged
    assert he.report.fallback.startswith("fire+smooth failed at 3 mmHg")


def test_the_fallback_skips_the_loads_after_one_it_could_not_close(valve, two_laws):
    """Both laws fail at 3 mmHg: the barrier path does not close 80 mmHg from the failed
    state (no equilibrium to continue from); the 80 mmHg report says it was skipped, is
    not converged and shows the state before it."""
    s = two_laws(smooth_limit=1.0, barrier_fails=RESULTS.stretch_limit)
    he, closed = closure.close_valve(valve, FALLBACK)
    assert s.calls == [("smooth", 3.0), ("barrier", 3.0)]
    assert not he.converged and not closed.converged
    assert closed.report.pressure == 80.0 and closed.report.steps == 0
    assert closed.report.state_pressure == he.report.state_pressure
    assert closed.report.result == he.report.result == "stretch_limit"
    np.testing.assert_array_equal(closed.x, he.x)
    assert closed.report.fallback.startswith("fire+smooth failed at 3 mmHg")


class CrossedOnFail(TwoLaws):
    """`TwoLaws` whose failed smooth closures end in a state that is no separated start
    (not finite here; crossed leaflets in the Gent valve of Table 5 at 0.1 MPa)."""

    def __call__(self, valve, material, p, *, x0, contact=None, **kw):
        sol = super().__call__(valve, material, p, x0=x0, contact=contact, **kw)
        if int(sol.result) != RESULTS.successful:
            x = np.asarray(sol.x, float).copy()
            x[0, 0] = np.nan
            sol = _sol(x, sol.result, 9)
        return sol


def test_the_fallback_swings_shut_under_a_lighter_load_where_the_smooth_state_is_unusable(
        valve, monkeypatch):
    """The smooth law fails at 3 mmHg in a state the barrier path cannot start from: the
    valve is swung shut by FIRE under he_pressure / 3 (then / 9), and the barrier
    closures start from the first separated one; where none is, from the placement."""
    make = _stand_in(monkeypatch, CrossedOnFail)
    s = make(smooth_limit=1.0)
    he, closed = closure.close_valve(valve, FALLBACK)
    assert s.calls == [("smooth", 3.0), ("smooth", 1.0), ("barrier", 3.0), ("barrier", 80.0)]
    assert he.converged and closed.converged
    s = make(smooth_limit=0.2)
    he, closed = closure.close_valve(valve, FALLBACK)
    # then the watched swing at 3 mmHg (`watched_swing`), unseparated after its first round
    assert s.calls == [("smooth", 3.0), ("smooth", 1.0), ("smooth", pytest.approx(1 / 3)),
                       ("smooth", 3.0), ("barrier", 3.0), ("barrier", 80.0)]
    assert closure.SWING_FRACTIONS[0] == 1.0     # the barrier path's own swing: he first


class WatchedRounds(CrossedOnFail):
    """`CrossedOnFail` whose FIRE runs of `closure.WATCH_STEPS` steps (the watched swing's
    rounds) each move the state 0.1 mm on and stop at their cap, separated for the first
    ``separated_rounds`` rounds and not finite after; the barrier solves log their x0."""

    def __init__(self, separated_rounds=2, **kw):
        super().__init__(**kw)
        self.rounds, self.separated_rounds, self.barrier_x0 = 0, separated_rounds, []

    def __call__(self, valve, material, p, *, x0, contact=None, solver=None, **kw):
        barrier = getattr(contact, "barrier", False)
        if not barrier and getattr(solver, "max_steps", None) == closure.WATCH_STEPS:
            self.calls.append(("watched", float(p)))
            self.rounds += 1
            x = np.asarray(x0, float) + np.array([0.1, 0.0, 0.0])
            if self.rounds > self.separated_rounds:
                x[0, 0] = np.nan
            return _sol(x, RESULTS.max_steps_reached, closure.WATCH_STEPS)
        if barrier:
            self.barrier_x0.append(np.asarray(x0, float).copy())
        return super().__call__(valve, material, p, x0=x0, contact=contact, solver=solver,
                                **kw)


class LoggedStarts(CrossedOnFail):
    """`CrossedOnFail` that logs the start x0 of every call beside (law, pressure)."""

    def __init__(self, **kw):
        super().__init__(**kw)
        self.starts = []

    def __call__(self, valve, material, p, *, x0, **kw):
        self.starts.append(np.asarray(x0, float).copy())
        return super().__call__(valve, material, p, x0=x0, **kw)


def test_a_given_start_that_is_no_separated_start_gives_way_to_the_placement(
        valve, monkeypatch):
    """A closure from a given start whose leaflets cross (not finite here; the stress
    suite pushes them through one another): the smooth law's closure fails, and the
    barrier path's swing-shut starts from the placement, not from the given start, which
    would leave the swing crossed and give the barrier no start."""
    s = _stand_in(monkeypatch, LoggedStarts)(smooth_limit=1.0)
    bad = np.asarray(valve.x_start, float).copy()
    bad[0, 1] = np.nan
    (closed,) = closure.close_valve(valve, FALLBACK, x0=bad, pressures=(80.0,))
    assert s.calls == [("smooth", 80.0), ("smooth", 1.0), ("barrier", 80.0)]
    assert closed.converged and closed.report.fallback
    np.testing.assert_array_equal(s.starts[0], bad)
    np.testing.assert_array_equal(s.starts[1], np.asarray(valve.x_start, float))
    assert np.all(np.isfinite(s.starts[2]))


def test_where_no_swing_converges_separated_the_barrier_starts_from_the_last_separated_fire_state(
        valve, monkeypatch):
    """Every swing ends unseparated: the watched FIRE swing at he_pressure, checked every
    WATCH_STEPS steps, hands its last separated state to the barrier closures (the state
    after 2 rounds here: 0.2 mm on from the placement), which close from it at 3 mmHg."""
    scene = FALLBACK.replace(max_steps=1000)        # room for 5 rounds
    s = _stand_in(monkeypatch, WatchedRounds)(smooth_limit=0.2)
    he, closed = closure.close_valve(valve, scene)
    assert s.calls[3:] == [("watched", 3.0)] * 3 + [("barrier", 3.0), ("barrier", 80.0)]
    np.testing.assert_allclose(s.barrier_x0[0], np.asarray(valve.x_start, float)
                               + np.array([0.2, 0.0, 0.0]), rtol=0, atol=1e-12)
    assert he.converged and closed.converged
    # a swing unseparated after its first round gives no start: the placement
    s = _stand_in(monkeypatch, WatchedRounds)(smooth_limit=0.2, separated_rounds=0)
    closure.close_valve(valve, scene)
    assert s.calls.count(("watched", 3.0)) == 1
    np.testing.assert_array_equal(s.barrier_x0[0], np.asarray(valve.x_start, float))
    with pytest.raises(ValueError, match="every must be a positive integer"):
        closure.watched_swing(valve, scene, valve.x_start, every=0)


class BarrierCapped(CrossedOnFail):
    """`CrossedOnFail` whose barrier solves stop at their step cap above 2.5 mmHg."""

    def __call__(self, valve, material, p, *, x0, contact=None, **kw):
        sol = super().__call__(valve, material, p, x0=x0, contact=contact, **kw)
        if getattr(contact, "barrier", False) and p > 2.5:
            sol = _sol(np.asarray(sol.x), RESULTS.max_steps_reached, 200)
        return sol


def test_the_first_barrier_load_continues_from_the_lighter_swing_pressure(valve, monkeypatch):
    """After a swing-shut at 1 mmHg the 3 mmHg barrier closure's continuation cuts its
    step between 1 and 3 mmHg (2 mmHg first), never below the swing's pressure."""
    s = _stand_in(monkeypatch, BarrierCapped)(smooth_limit=1.0)
    he, closed = closure.close_valve(valve, FALLBACK)
    barrier = [p for law, p in s.calls if law == "barrier"]
    assert barrier[:3] == [3.0, 2.0, 3.0] and min(barrier) >= 1.0
    assert not he.converged and he.report.result == "max_steps_reached"


def test_no_fallback_at_a_limit_point_or_when_switched_off(valve, two_laws, scripted):
    """A limit point is the membrane's: the barrier law is not tried.  Nor is it with
    ``fallback=False``, or in float32 (the barrier path is float64 only)."""
    s = scripted(limit=P_LIM)
    he, lim = closure.close_valve(valve, FALLBACK)
    assert lim.limit_point and lim.report.path == "fire+smooth" and not lim.report.fallback
    for scene in (SCENE, FALLBACK.replace(precision="float32")):
        s = two_laws()
        he, closed = closure.close_valve(valve, scene)
        assert not closed.converged and closed.report.result == "max_steps_reached"
        assert all(law == "smooth" for law, _ in s.calls) and not closed.report.fallback


def test_the_fallback_counts_the_failed_attempts_time(valve, monkeypatch, two_laws):
    two_laws()
    ticks = iter(range(0, 1000, 10))           # every perf_counter call: +10 s
    monkeypatch.setattr(closure, "time", types.SimpleNamespace(
        perf_counter=lambda: float(next(ticks))))
    he, closed = closure.close_valve(valve, FALLBACK)
    # each close_load spans one interval of 10 s: the 80 mmHg report holds the smooth
    # attempt's and the barrier closure's
    assert closed.report.wall_s == pytest.approx(20.0)
    assert he.report.wall_s == pytest.approx(20.0)


def test_scene_fallback_is_validated():
    from jaxvalve.errors import ParameterError
    with pytest.raises(ParameterError, match="fallback must be true or false"):
        Scene(fallback="yes")


def test_a_batch_members_failed_first_attempt_falls_back(valve, two_laws):
    """`simulate_batch` hands in its batched attempts: a member whose 80 mmHg attempt
    stopped at the step cap is closed again on the barrier law, both loads."""
    s = two_laws(smooth_limit=100.0)
    x = np.asarray(valve.x_start, float)
    given = (_sol(x + 3.0, RESULTS.successful, 11), _sol(x + 4.0, RESULTS.max_steps_reached,
                                                         FALLBACK.max_steps))
    he, closed = closure.close_valve(valve, FALLBACK, first=given)
    assert s.calls == [("barrier", 3.0), ("barrier", 80.0)]
    assert closed.converged and closed.report.path == "newton+barrier"
    assert f"max_steps_reached, residual 1.00e-06, {FALLBACK.max_steps} steps" in \
        closed.report.fallback


class RunsAway(TwoLaws):
    """`TwoLaws` with a fold: the smooth law converges up to 20 mmHg, stops at its step
    cap just above, and runs away from 22 mmHg; the barrier law converges up to 20.5
    mmHg and runs away above it."""

    def __call__(self, valve, material, p, *, x0, contact=None, **kw):
        sol = super().__call__(valve, material, p, x0=x0, contact=contact, **kw)
        barrier = self.calls[-1][0] == "barrier"
        if (barrier and p > 20.5) or (not barrier and p >= 22.0):
            sol = _sol(np.asarray(sol.x), RESULTS.escaped, 11)
        return sol


def test_the_fallback_ramp_tries_the_failed_paths_runaway_first(valve, monkeypatch):
    """The smooth path's 80 mmHg ramp ran away down to 22.25 mmHg and then failed at its
    step cap: the barrier ramp, after its own runaway at 80, tries 22.25 next instead
    of halving through 41.5 (`continuation.ramp`'s hint), and brackets the limit itself."""
    s = _stand_in(monkeypatch, RunsAway)()
    he, lim = closure.close_valve(valve, FALLBACK)
    smooth = [p for law, p in s.calls if law == "smooth"]
    barrier = [p for law, p in s.calls if law == "barrier"]
    assert smooth[:4] == [3.0, 80.0, 41.5, 22.25]
    assert barrier[:3] == [3.0, 80.0, 22.25] and 41.5 not in barrier
    assert lim.limit_point and lim.report.path == "newton+barrier"
    assert 20.3 <= lim.report.limit_pressure <= 20.5
