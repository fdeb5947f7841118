"""Continuation in pressure and the limit point (`jaxvalve.solvers.continuation`).

An inflated neo-Hookean sphere (R, H, mu) has an exact pressure-stretch curve,
P = 2 mu H / R (1/lambda - 1/lambda^7), with a maximum at lambda = 7^(1/6): above it no
equilibrium exists.  The icosphere's flat facets inflate like a sphere of the effective
radius 3 V0 / A0 (`tests/test_validation.py`), so its limit pressure is the analytic one
at that radius.  `ramp` must bracket it to its tolerance, report the state at the highest
equilibrium, and never call a failure of another kind a limit point.
"""
import numpy as np
import pytest
import jax.numpy as jnp

import analytic
from jaxvalve.geometry import meshgen
from jaxvalve.solvers.continuation import Ramp, ramp
from jaxvalve.solvers.equilibrium import solve
from jaxvalve.errors import ParameterError
from jaxvalve.mechanics.materials import NeoHookean
from jaxvalve.mechanics.problem import Params, make_problem
from jaxvalve.solvers import FIRE, RESULTS

R, H, MU = 5.0, 0.3, 0.1


@pytest.fixture(scope="module")
def sphere():
    p, t = meshgen.icosphere(R, 2)
    prob, ref = make_problem(p, t)
    V0 = np.sum(np.einsum("ij,ij->i", p[t[:, 0]], np.cross(p[t[:, 1]], p[t[:, 2]]))) / 6
    A0 = 0.5 * np.sum(np.linalg.norm(np.cross(p[t[:, 1]] - p[t[:, 0]],
                                               p[t[:, 2]] - p[t[:, 0]]), axis=1))
    r_eff = 3 * V0 / A0
    p_max = float(analytic.sphere_pressure_neo_hookean(analytic.NEO_HOOKEAN_LIMIT_STRETCH,
                                                       MU, H, r_eff))
    return prob, ref, jnp.asarray(p), p_max, r_eff


def _solver(prob, ref, solver):
    def run(P, x):
        params = Params(ref=ref, material=NeoHookean(MU), thickness=H, pressure=P)
        return solve(prob, params, jnp.asarray(x), solver, throw=False)
    return run


def _stretch(x):
    x = np.asarray(x)
    return np.linalg.norm(x - x.mean(0), axis=1).mean() / R


def test_a_load_past_the_limit_runs_away(sphere):
    prob, ref, x0, p_max, r_eff = sphere
    run = _solver(prob, ref, FIRE(rtol=1e-8, max_steps=20_000))
    below, above = run(0.99 * p_max, x0), run(1.01 * p_max, x0)
    print(f"\nsphere, FIRE: 0.99 P_max {RESULTS(int(below.result)).name} in "
          f"{int(below.stats.steps)} steps; 1.01 P_max {RESULTS(int(above.result)).name} "
          f"in {int(above.stats.steps)} steps, stretch {_stretch(above.x):.2f}")
    assert below.converged and _stretch(below.x) < analytic.NEO_HOOKEAN_LIMIT_STRETCH
    # 1 % above the limit the sphere inflates until a node has moved a diameter
    assert int(above.result) == RESULTS.escaped
    assert _stretch(above.x) > 2.9


def test_ramp_brackets_the_analytic_limit_point(sphere):
    prob, ref, x0, p_max, r_eff = sphere
    out = ramp(_solver(prob, ref, FIRE(rtol=1e-8, max_steps=20_000)), x0, 2.0 * p_max,
               settings=Ramp(rtol=0.005))
    print(f"\nramp: {out.status}, bracket [{out.pressure:.7g}, {out.p_escape:.7g}] MPa, "
          f"analytic P_max {p_max:.7g} MPa, {len(out.history)} solves")
    assert out.status == "limit_point" and not out.converged
    # the bracket holds the analytic limit of the effective sphere to 0.2 % (the discrete
    # limit lies 1e-4 below it: the flat-facet radius is not exact at this stretch)
    assert out.pressure < out.p_escape
    assert out.pressure < 1.002 * p_max and out.p_escape > 0.998 * p_max
    assert out.p_escape - out.pressure <= 0.005 * out.p_escape
    assert out.solution.converged
    # the reported state is the equilibrium at the reported pressure, on the stable branch
    lam = _stretch(out.x)
    assert abs(lam - analytic.inflated_sphere_stretch(out.pressure, MU, H, r_eff)) < 0.05
    assert lam < analytic.NEO_HOOKEAN_LIMIT_STRETCH * 1.02
    results = [h[1] for h in out.history]
    assert set(results) == {"successful", "escaped"}
    assert "limit_point" in out.describe() and f"{out.pressure:.4g}" in out.describe()
    assert out.final == (out.solution, out.pressure)


def test_ramp_below_the_limit_converges_in_one_solve(sphere):
    prob, ref, x0, p_max, r_eff = sphere
    out = ramp(_solver(prob, ref, FIRE(rtol=1e-8, max_steps=20_000)), x0, 0.9 * p_max)
    assert out.converged and out.pressure == 0.9 * p_max and len(out.history) == 1
    lam = analytic.inflated_sphere_stretch(0.9 * p_max, MU, H, r_eff)
    assert abs(_stretch(out.x) - lam) < 0.02 * lam


def test_another_failure_is_never_called_a_limit_point(sphere):
    prob, ref, x0, p_max, r_eff = sphere
    # five FIRE steps cannot converge anywhere: the ramp stops at the first failure
    out = ramp(_solver(prob, ref, FIRE(rtol=1e-8, max_steps=5)), x0, 0.5 * p_max)
    assert out.status == "max_steps_reached" and out.pressure == 0.0
    assert out.solution is None and int(out.failure.result) == RESULTS.max_steps_reached
    assert "max_steps_reached" in out.describe()
    assert out.final == (out.failure, 0.5 * p_max)


def test_no_equilibrium_above_the_start_is_not_a_limit_point(sphere):
    prob, ref, x0, p_max, r_eff = sphere
    # every pressure above 1.005 P_max runs away; the unloaded start is no equilibrium at
    # 1.005 P_max, so there is no equilibrium to report: 'escaped', with the runaway shown
    out = ramp(_solver(prob, ref, FIRE(rtol=1e-8, max_steps=20_000)), x0, 2.0 * p_max,
               p_start=1.005 * p_max)
    assert out.status == "escaped" and out.solution is None
    assert {h[1] for h in out.history} == {"escaped"}
    assert out.p_escape - out.pressure <= 0.01 * out.p_escape
    sol, p = out.final
    assert sol is out.failure and p == out.history[-1][0]


def test_ramp_rejects_bad_settings(sphere):
    prob, ref, x0, p_max, r_eff = sphere
    with pytest.raises(ParameterError, match="rtol"):
        Ramp(rtol=0.0)
    with pytest.raises(ParameterError, match="max_solves"):
        Ramp(max_solves=0)
    with pytest.raises(ParameterError, match="p_target > p_start"):
        ramp(lambda p, x: None, x0, 1.0, p_start=2.0)


def test_solve_report_names_the_limit_point_and_the_state_pressure():
    from jaxvalve.simulation import SolveReport
    lim = SolveReport(pressure=80.0, result="limit_point", converged=False, steps=900,
                      residual=5e-5, wall_s=1.0, compile_s=0.5, limit_pressure=11.25,
                      state_pressure=11.25)
    assert lim.describe().startswith("limit_point: no equilibrium above 11.2 mmHg")
    bad = SolveReport(pressure=80.0, result="max_steps_reached", converged=False, steps=9,
                      residual=2e-3, wall_s=1.0, compile_s=0.5, state_pressure=12.6)
    assert "max_steps_reached (state at 12.6 mmHg)" in bad.describe()
    ok = SolveReport(pressure=80.0, result="successful", converged=True, steps=9,
                     residual=2e-5, wall_s=1.0, compile_s=0.5, state_pressure=80.0)
    assert ok.describe() == "converged, residual 2.00e-05, 9 steps"


class _Stalls:
    """A stand-in solve that stagnates where the load step from its start state exceeds
    ``reach`` (a Newton line search defeated by a long increment) and else converges;
    the state is its pressure.  Records the pressures tried."""

    def __init__(self, reach):
        self.reach, self.tried = reach, []

    def __call__(self, p, x):
        from jaxvalve.solvers import Solution, Stats
        self.tried.append(p)
        ok = p - float(x[0]) <= self.reach
        code = RESULTS.successful if ok else RESULTS.stagnation
        stats = Stats(steps=10, force_evals=10, hvps=0, residual=1e-9 if ok else 0.2)
        return Solution(x=np.array([p if ok else float(x[0])]), result=int(code), stats=stats)


def test_a_stagnated_step_is_retried_at_half_the_increment_then_at_its_own_pressure():
    s = _Stalls(reach=25.0)
    out = ramp(s, np.array([3.0]), 80.0, 3.0)
    assert out.converged and out.pressure == 80.0 and float(out.x[0]) == 80.0
    # 80 and 41.5 too far from 3; 22.25 reached; 41.5 again from there; 80 too far from
    # 41.5; 60.75; 80
    assert s.tried == [80.0, 41.5, 22.25, 41.5, 80.0, 60.75, 80.0]
    assert [h[1] for h in out.history].count("stagnation") == 3


def test_a_ramp_out_of_solves_after_an_equilibrium_reports_the_failure_before_it():
    """Out of solves just after an equilibrium below the target, the ramp reports the
    failure that made it step (no runaway happened, so never `escaped`)."""
    s = _Stalls(reach=25.0)
    out = ramp(s, np.array([3.0]), 80.0, 3.0, Ramp(max_solves=4))
    assert s.tried == [80.0, 41.5, 22.25, 41.5]
    assert out.status == "stagnation" and out.pressure == 41.5 and out.p_escape is None
    assert out.failure is not None and not out.failure.converged


def test_a_ramp_that_stalls_is_reported_as_stagnation_never_as_a_limit_point():
    # increments of 0.1 converge: the ramp creeps up and runs out of solves
    s = _Stalls(reach=0.1)
    out = ramp(s, np.array([3.0]), 80.0, 3.0, Ramp(rtol=0.01, max_solves=30))
    assert out.status == "stagnation" and not out.converged and not out.limit_point
    assert len(s.tried) == 30 and 3.0 < out.pressure < 4.0
    assert out.p_escape is None
    # no increment converges and the stall comes within rtol of the start: stagnation
    s = _Stalls(reach=0.0)
    out = ramp(s, np.array([3.0]), 80.0, 3.0, Ramp(rtol=0.01))
    assert out.status == "stagnation" and out.pressure == 3.0
    assert s.tried[-1] - 3.0 <= 0.01 * s.tried[-1] < s.tried[-2] - 3.0


def test_a_solver_may_declare_its_step_cap_a_load_step_too_long():
    """The engine declares `max_steps_reached` a step too long (cut_on); FIRE
    declares nothing (neither its cap nor its stagnation), so its cap ends the ramp."""
    from jaxvalve.solvers.continuation import CUT_ON, cut_on
    from jaxvalve.solvers.equilibrium import Engine

    class Capped(_Stalls):
        def __call__(self, p, x):
            sol = super().__call__(p, x)
            code = RESULTS.successful if sol.converged else RESULTS.max_steps_reached
            return type(sol)(x=sol.x, result=int(code), stats=sol.stats)

    assert "max_steps_reached" in cut_on(Engine()) and "max_steps_reached" not in cut_on(FIRE())
    assert "stagnation" in CUT_ON
    s = Capped(reach=25.0)
    out = ramp(s, np.array([3.0]), 80.0, 3.0, cut=cut_on(Engine()))
    assert out.converged and s.tried == [80.0, 41.5, 22.25, 41.5, 80.0, 60.75, 80.0]
    s = Capped(reach=25.0)
    out = ramp(s, np.array([3.0]), 80.0, 3.0, cut=cut_on(FIRE()))
    assert out.status == "max_steps_reached" and s.tried == [80.0]


def test_a_barrier_step_that_lands_on_a_collapsed_triangle_is_cut():
    """A barrier closure whose state the valve's check rejects for a collapsed triangle
    (`inverted_triangles`) took too long a load step: the ramp retries it at half the
    increment, as after a step cap; a crossing (which the barrier rules out by
    construction, so its cause lies elsewhere) still ends the ramp."""
    import types
    from jaxvalve.solvers.equilibrium import Engine
    from jaxvalve.solvers.continuation import cut_on

    class Rejected(_Stalls):
        state = "inverted_triangles"

        def __call__(self, p, x):
            sol = super().__call__(p, x)
            if sol.converged:
                return sol
            # the solver met rtol, at a state the check rejects
            return types.SimpleNamespace(x=np.array([p]), converged=False,
                                         status=self.state, stats=sol.stats)

    assert "inverted_triangles" in cut_on(Engine())
    s = Rejected(reach=25.0)
    out = ramp(s, np.array([3.0]), 80.0, 3.0, cut=cut_on(Engine()))
    assert out.converged and s.tried == [80.0, 41.5, 22.25, 41.5, 80.0, 60.75, 80.0]
    assert float(out.x[0]) == 80.0
    s = Rejected(reach=25.0)
    s.state = "leaflets_cross"
    out = ramp(s, np.array([3.0]), 80.0, 3.0, cut=cut_on(Engine()))
    assert out.status == "leaflets_cross" and s.tried == [80.0]


def test_a_ramp_ends_when_its_step_budget_is_spent():
    """`Ramp.max_steps` bounds the solver steps of a ramp that creeps up (each solve 10
    steps here): it ends after the first failed solve past the budget, with that failure
    and the highest equilibrium reached; a ramp that converges within it is unchanged."""
    from jaxvalve.solvers.equilibrium import Engine
    s = _Stalls(reach=0.1)
    out = ramp(s, np.array([3.0]), 80.0, 3.0, Ramp(max_steps=55))
    assert out.status == "stagnation" and not out.converged and not out.limit_point
    assert 55 <= out.steps < 55 + 2 * 10 and len(s.tried) == out.steps // 10 < 30
    assert out.pressure == 3.0 and out.final[1] == s.tried[-1] == 3.0 + 77.0 / 2**5
    s = _Stalls(reach=25.0)
    assert ramp(s, np.array([3.0]), 80.0, 3.0, Ramp(max_steps=70)).converged
    assert Ramp.for_solver(Engine(max_steps=200)).max_steps == 2000
    assert Ramp.for_solver(object()).max_steps is None
    with pytest.raises(ParameterError, match="max_steps"):
        Ramp(max_steps=0)


class _Fold:
    """A stand-in solve with a fold at ``fold``: it converges at or below it, stalls at its
    step cap just above it (the slow drift through the ghost of the lost equilibrium, a
    failure the barrier Newton declares a load step too long), and runs away from
    ``runaway`` up.  The state is its pressure."""

    def __init__(self, fold=20.3, runaway=22.0, stall_steps=300):
        self.fold, self.runaway, self.stall_steps, self.tried = fold, runaway, stall_steps, []

    def __call__(self, p, x, max_steps=None):
        from jaxvalve.solvers import Solution, Stats
        self.tried.append(p)
        cap = self.stall_steps if max_steps is None else min(max_steps, self.stall_steps)
        if p <= self.fold:
            code, n, res, y = RESULTS.successful, 10, 1e-9, p
        elif p < self.runaway:
            code, n, res, y = RESULTS.max_steps_reached, cap, 3e-3, float(x[0])
        elif cap < 50:                    # stopped before it has gone far enough
            code, n, res, y = RESULTS.max_steps_reached, cap, 5.0, float(x[0])
        else:
            code, n, res, y = RESULTS.escaped, 50, 5.0, 1e3
        stats = Stats(steps=n, force_evals=n, hvps=0, residual=res)
        return Solution(x=np.array([y]), result=int(code), stats=stats)


def test_solves_that_stall_just_past_a_fold_under_a_runaway_end_at_a_limit_point():
    """Past a fold the state drifts slowly, and a Newton solve there ends at its step cap
    before it counts as a runaway: stalls within rtol of the highest equilibrium, under a
    pressure that ran away, are a limit point, bracketed like one.  Once a solve has run
    away the ramp's step budget no longer ends it (it only narrows a bracket then).
    Without a runaway the same stalls are reported as they are."""
    from jaxvalve.solvers.continuation import cut_on
    from jaxvalve.solvers.equilibrium import Engine
    cut = cut_on(Engine())
    s = _Fold()
    out = ramp(s, np.array([3.0]), 80.0, 3.0, Ramp(max_steps=1000), cut=cut)
    assert out.status == "limit_point" and out.limit_point and not out.converged
    assert out.pressure <= s.fold < out.p_stall < s.runaway <= out.p_escape
    assert out.p_stall - out.pressure <= 0.01 * out.p_stall
    assert out.steps > 1000                  # past the budget, which no longer applies
    assert float(out.x[0]) == out.pressure and out.final == (out.solution, out.pressure)
    assert f"solves from {out.p_stall:.4g} stalled" in out.describe()
    # the same stalls with no runaway above them: the step cap, never a limit point
    s = _Fold(runaway=np.inf)
    out = ramp(s, np.array([3.0]), 80.0, 3.0, Ramp(max_steps=100_000), cut=cut)
    assert out.status == "max_steps_reached" and not out.limit_point
    assert out.p_escape is None and out.pressure <= s.fold
    # and the budget still ends a ramp that has seen no runaway
    s = _Fold(runaway=np.inf)
    out = ramp(s, np.array([3.0]), 80.0, 3.0, Ramp(max_steps=1000), cut=cut)
    assert out.status == "max_steps_reached" and 1000 <= out.steps < 1000 + 300


def test_under_a_runaway_a_twice_stalled_pressure_bounds_the_bracket():
    """Once a solve has run away, a pressure under it that stalls is solved once more
    from the next, nearer equilibrium (far below a fold a stall is often a load step
    too long); stalled twice, it is an end of the bracket like the runaway: the ramp
    bisects below it and solves it again only from an equilibrium within rtol of it, not
    after every equilibrium (each such solve is a full solve to the step cap).  The fold
    of the 0.1 MPa springs (template (a), h = 2 mm): equilibria up to 46.0 mmHg, stalls
    at 46.3, a runaway at 51.1."""
    from jaxvalve.solvers.continuation import cut_on
    from jaxvalve.solvers.equilibrium import Engine
    s = _Fold(fold=46.1, runaway=51.1)
    out = ramp(s, np.array([3.0]), 80.0, 3.0, Ramp(max_steps=1000),
               cut=cut_on(Engine()))
    assert out.limit_point and out.pressure <= s.fold < out.p_stall < s.runaway
    assert out.p_stall - out.pressure <= 0.01 * out.p_stall
    hist = out.history
    for i, (q, status, *_) in enumerate(hist):
        before = [h for h in hist[:i] if h[0] == q and h[1] == "max_steps_reached"]
        if len(before) >= 2:              # a third solve of a twice-stalled pressure
            p_prev, st_prev = hist[i - 1][:2]
            assert st_prev == "successful" and q - p_prev <= 0.01 * q, hist
    stalls = [h for h in hist if h[1] == "max_steps_reached"]
    assert len(stalls) == 3 and out.steps == 1100   # retried after every equilibrium: 5, 1700


def test_a_bracket_closed_from_below_by_equilibria_ends_at_the_limit_point():
    """Where the fold lies just under a runaway, every midpoint under it converges and the
    bracket closes from below: the ramp ends at a limit point as soon as it is narrower
    than rtol, instead of creeping up to the runaway until its solves run out (the stress
    suite's neo-Hookean valve on template (c), 0.1 MPa at 80 mmHg: a runaway at 22.25
    mmHg, then 27 equilibria up to 22.2 mmHg, reported as `escaped`)."""
    from jaxvalve.solvers.equilibrium import Engine
    from jaxvalve.solvers.continuation import cut_on

    class StallsAtTarget(_Fold):
        # that valve's first solve, at the target, ended at its step cap before it ran
        # away: a stall above the runaway, which must not keep the bracket open
        def __call__(self, p, x, max_steps=None):
            return super().__call__(p, x, 10 if p == 80.0 else max_steps)

    for s, first in ((_Fold(fold=22.249, runaway=22.25), "escaped"),
                     (StallsAtTarget(fold=22.249, runaway=22.25), "max_steps_reached")):
        out = ramp(s, np.array([3.0]), 80.0, 3.0, cut=cut_on(Engine()))
        assert out.history[0][1] == first
        assert s.tried[:3] == [80.0, 41.5, 22.25]        # 22.25 is the midpoint of 3-41.5
        assert out.status == "limit_point" and out.p_escape == 22.25 and out.p_stall is None
        assert out.p_escape - out.pressure <= 0.01 * out.p_escape
        assert out.solution.converged and float(out.x[0]) == out.pressure
        assert out.failure is not None and out.failure.status == "escaped"
        # the first equilibrium within 1 % of the runaway ends it
        within = [p for p in s.tried if p < 22.25 and 22.25 - p <= 0.01 * 22.25]
        assert s.tried[-1] == within[0] and len(s.tried) <= 12
