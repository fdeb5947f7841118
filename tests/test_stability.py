"""Stability of a converged equilibrium (`barrier_newton.lowest_modes`) and the push off an
unstable one: a flat clamped disk compressed in its plane is an equilibrium that buckles
out of plane (a negative eigenvalue, its mode out of plane); stretched, it is stable; the
solve pushes the compressed disk off its flat state and ends at a buckled, stable one."""
import numpy as np
import pytest

from jaxvalve.geometry import meshgen
from jaxvalve.mechanics.bending import Bending
from jaxvalve.contact.barrier import BarrierContact
from jaxvalve.contact.ipc_pairs import barrier_topology, build_pairs
from jaxvalve.mechanics.materials import StVenantKirchhoff
from jaxvalve.mechanics.problem import Params, make_problem
from jaxvalve.solvers import RESULTS, BarrierNewton, solve_barrier
from jaxvalve.solvers.barrier_newton import _Model, lowest_modes

R = 5.0


def _disk(scale):
    """(problem, params, topology, x): a clamped disk of radius R mm, flat, with its
    reference ``scale`` times the placed size (> 1: compressed in its plane)."""
    p, t, edge = meshgen.disk(R, 4)
    prob, ref = make_problem(scale * p, t, fixed=edge)
    params = Params(ref=ref, material=StVenantKirchhoff(1.0, 0.45), thickness=0.1, pressure=0.0,
                    contact=BarrierContact(), bending=Bending())
    x = np.asarray(meshgen.lift(p), float)
    topo = barrier_topology(t, np.zeros(len(p), int), scale * p, edge, x)
    return prob, params, topo, x


@pytest.mark.parametrize("scale, stable", [(1.02, False), (0.98, True)])
def test_a_compressed_flat_disk_is_an_unstable_equilibrium_and_a_stretched_one_stable(
        scale, stable):
    prob, params, topo, x = _disk(scale)
    model = _Model(prob, params, topo)
    pairs = build_pairs(topo, x, float(params.contact.dhat))
    E, F, _ = model.evaluate(x, pairs)
    assert np.abs(F).max() < 1e-12                       # flat and uniform: in equilibrium
    lam, v = lowest_modes(model, x, pairs)
    assert (lam > 0) == stable, lam
    if not stable:                                       # the buckling mode is out of plane
        assert np.abs(v[:, 2]).max() == pytest.approx(1.0)
        assert np.abs(v[:, :2]).max() < 1e-6


def test_the_solve_pushes_off_an_unstable_equilibrium_to_a_stable_one():
    prob, params, topo, x = _disk(1.02)
    sol, log = solve_barrier(prob, params, x,
                             BarrierNewton(rtol=1e-8, max_steps=300, max_pushes=10), topo)
    assert int(sol.result) == RESULTS.successful, (sol.describe(), log.stability)
    # one push: after it every step lowers the merit, away from the saddle (with the
    # residual test for Newton-Krylov steps as well, six pushes went saddle to saddle)
    assert len(log.stability) == 2 and log.stability[0][1] < 0 <= log.stability[1][1]
    assert np.abs(np.asarray(sol.x)[:, 2]).max() > 0.1          # buckled out of plane
    # a pushed state is not an equilibrium: with too few steps left it is not converged
    short, _ = solve_barrier(prob, params, x,
                             BarrierNewton(rtol=1e-8, max_steps=3, max_pushes=10), topo)
    assert int(short.result) == RESULTS.max_steps_reached, short.describe()
    # without the check (the default) the flat state is returned as it is
    sol0, log0 = solve_barrier(prob, params, x, BarrierNewton(), topo)
    assert int(sol0.result) == RESULTS.successful and not log0.stability
    assert np.abs(np.asarray(sol0.x)[:, 2]).max() == 0.0


def test_a_solve_whose_best_residual_stops_halving_ends_at_its_patience():
    """Patience: a solve below exact_below whose best residual has not halved for
    `patience` steps ends as `stagnation` (continuation then cuts the load step), not at
    its step cap.  Here the inflated disk reaches the round-off floor (3.5e-14), below
    which rtol = 1e-16 cannot be met: with patience 0 it runs to its cap."""
    prob, params, topo, x = _disk(0.98)
    params = params.replace(pressure=1e-3)
    capped, _ = solve_barrier(prob, params, x,
                              BarrierNewton(rtol=1e-16, max_steps=60, patience=0), topo)
    assert int(capped.result) == RESULTS.max_steps_reached
    sol, log = solve_barrier(prob, params, x,
                             BarrierNewton(rtol=1e-16, max_steps=60, patience=5), topo)
    assert int(sol.result) == RESULTS.stagnation, sol.describe()
    n = int(sol.stats.steps)
    assert n < 30
    r = np.asarray(log.residual)
    assert r.min() < 1e-12 and r[-6:].min() > 0.5 * r[:-6].min()   # no halving in 5+1
    assert float(sol.stats.residual) <= 2.0 * float(capped.stats.residual)
    assert "stagnation" in BarrierNewton().cut_on
