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

SCENE = Scene(h=3.0, max_steps=100)
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
    # too long (`continuation.cut_on`: the engine's finish may pass from nearer): the
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
