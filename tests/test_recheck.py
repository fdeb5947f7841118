"""equilibrium.solve checks every converged result with a program of its own (the
residual by autodiff of the energies): a compiled loop that claims an equilibrium it does
not have is reported as `RESULTS.inconsistent`, never as a silent equilibrium."""
import dataclasses
import logging

import jax.numpy as jnp
import pytest

from jaxvalve.solvers import equilibrium

from jaxvalve.geometry import meshgen
from jaxvalve.errors import ConvergenceError
from jaxvalve.mechanics.materials import Gent
from jaxvalve.mechanics.problem import Params, make_problem, mmhg
from jaxvalve.solvers import FIRE, RESULTS

#: how many times each lying solver class was traced (a Python side effect of tracing)
TRACES = {}


@dataclasses.dataclass(frozen=True)
class LiarFIRE(FIRE):
    """FIRE whose loop stops after its first real step claiming convergence, in the first
    ``lies`` compilations of the class (a stand-in for a miscompiled loop)."""

    lies: int = 10**9

    def terminate(self, system, y, args, s):
        n = TRACES[self.lies] = TRACES.get(self.lies, 0) + 1
        if n > self.lies:
            return super().terminate(system, y, args, s)
        return s["n"] >= 2, jnp.asarray(RESULTS.successful)


@pytest.fixture(scope="module")
def membrane():
    p, t, b = meshgen.disk(5.0, 2)
    prob, ref = make_problem(p, t, fixed=b)
    params = Params(ref=ref, material=Gent(mu=1 / 3, Jm=0.3), thickness=0.3,
                    pressure=mmhg(80.0))
    return prob, params, jnp.asarray(meshgen.lift(p))


def test_a_loop_that_claims_a_false_equilibrium_is_reported_inconsistent(membrane, caplog):
    prob, params, x0 = membrane
    with caplog.at_level(logging.WARNING, logger="jaxvalve"):
        sol = equilibrium.solve(prob, params, x0, LiarFIRE(rtol=1e-8), throw=False)
    assert int(sol.result) == RESULTS.inconsistent and not sol.converged
    # the reported residual is the independent one: after 2 FIRE steps from the flat
    # membrane the free nodes still carry most of the pressure load
    assert 0.1 < float(sol.stats.residual) < 10.0, sol.describe()
    assert "independent evaluation" in caplog.text
    with pytest.raises(ConvergenceError, match="inconsistent"):
        equilibrium.solve(prob, params, x0, LiarFIRE(rtol=1e-8), throw=True)


def test_a_true_equilibrium_passes_the_recheck(membrane):
    prob, params, x0 = membrane
    sol = equilibrium.solve(prob, params, x0, FIRE(rtol=1e-8), throw=False)
    assert sol.converged and equilibrium._recheck(prob, params, sol, 1e-8) is sol
    # the same state under another material is no equilibrium (past a lower stretch
    # limit, not even finite): not sound, whatever the loop said
    tight = params.replace(material=Gent(mu=1 / 3, Jm=1e-3))
    bad = equilibrium._recheck(prob, tight, sol, 1e-8)
    assert int(bad.result) == RESULTS.inconsistent and not bad.converged
