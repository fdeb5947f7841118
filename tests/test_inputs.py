"""Bad input gets a clear error that names the parameter and its valid range."""
import jax.numpy as jnp
import numpy as np
import pytest

from jaxvalve.solvers import equilibrium

from jaxvalve.geometry import meshgen
from jaxvalve.errors import MeshError, ParameterError
from jaxvalve.mechanics.materials import Gent, MassSpring, NeoHookean, StVenantKirchhoff
from jaxvalve.mechanics.problem import Params, make_problem, validate_params
from jaxvalve.solvers import FIRE, FixedPoint, NewtonKrylov
from jaxvalve.solvers.equilibrium import Engine
from jaxvalve.solvers.predictor import BulgePredictor

P, T = meshgen.rectangle(2.0, 1.0, 2, 1)


@pytest.mark.parametrize("ref,tri,match", [
    (P, np.array([[0, 1, 99]]), r"indices must lie in \[0, 5\]"),
    (P, np.array([[0, -1, 2]]), "indices must lie"),
    (P, np.array([[0, 0, 2]]), "3 distinct nodes"),
    (np.array([[0, 0], [1, 0], [2, 0.0]]), np.array([[0, 1, 2]]), "degenerate"),
    (np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0.0]]), np.array([[0, 1, 2]]), "degenerate"),
    (P, T[:, [0, 2, 1]], "clockwise"),
    (np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.0]]), np.array([[0, 1, 2], [1, 2, 3]]),
     "same direction"),
    (np.where(np.arange(P.size).reshape(P.shape) == 3, np.nan, P), T, "non-finite"),
    (P[:, :1], T, "shape"),
    (P, T[:, :2], "shape"),
])
def test_broken_mesh_is_rejected(ref, tri, match):
    with pytest.raises(MeshError, match=match):
        make_problem(ref, tri)


def test_inconsistent_2d_orientation_is_rejected():
    tri = T.copy()
    tri[0] = tri[0, [0, 2, 1]]
    with pytest.raises(MeshError, match="clockwise"):
        make_problem(P, tri)


def test_all_fixed_and_mixed_bodies_are_rejected():
    with pytest.raises(MeshError, match="free"):
        make_problem(P, T, fixed=np.ones(len(P), bool))
    with pytest.raises(MeshError, match="body"):
        make_problem(P, T, body=np.arange(len(P)))


@pytest.mark.parametrize("mat,match", [
    (StVenantKirchhoff(E=0.0, nu=0.3), "E must be > 0"),
    (StVenantKirchhoff(E=-1.0, nu=0.3), "E must be > 0"),
    (StVenantKirchhoff(E=1.0, nu=0.6), r"nu must lie in \(-1, 0.5\]"),
    (StVenantKirchhoff(E=1.0, nu=-1.0), r"nu must lie in \(-1, 0.5\]"),
    (StVenantKirchhoff(E=float("nan"), nu=0.3), "E must be finite"),
    (NeoHookean(mu=-0.1), "mu must be > 0"),
    (Gent(mu=0.3, Jm=0.0), "Jm must be > 0"),
    (MassSpring(E1=0.1, E2=-0.5, E3=1.0), "E2 must be > 0"),
    (MassSpring(E1=0.1, E2=0.5, E3=1.0, break1=0.4, break2=0.3), "break1 <= break2"),
])
def test_bad_moduli_are_rejected(mat, match):
    prob, ref = make_problem(P, T)
    with pytest.raises(ParameterError, match=match):
        validate_params(Params(ref=ref, material=mat))


def test_bad_thickness_pressure_and_start_are_rejected():
    prob, ref = make_problem(P, T, fixed=[0, 3])
    good = Params(ref=ref, material=NeoHookean(0.3))
    with pytest.raises(ParameterError, match="thickness H must be > 0"):
        validate_params(good.replace(thickness=0.0))
    with pytest.raises(ParameterError, match="pressure P must be finite"):
        validate_params(good.replace(pressure=float("nan")))
    x0 = jnp.asarray(meshgen.lift(P))
    with pytest.raises(ParameterError, match="x0 holds a non-finite"):
        equilibrium.solve(prob, good, x0.at[1, 2].set(jnp.nan))
    with pytest.raises(ParameterError, match=r"x0 must have shape \(6, 3\)"):
        equilibrium.solve(prob, good, x0[:, :2])


@pytest.mark.parametrize("make, match", [
    (lambda: FIRE(rtol=0.0), r"FIRE\.rtol must be finite and > 0; got 0\.0"),
    (lambda: FIRE(rtol=float("nan")), r"FIRE\.rtol must be finite"),
    (lambda: FIRE(max_steps=1e4), r"FIRE\.max_steps must be an integer >= 0"),
    (lambda: FIRE(f_dec=1.0), r"FIRE\.f_dec must be in \(0, 1\)"),
    (lambda: FIRE(f_inc=0.9), r"FIRE\.f_inc must be finite and > 1"),
    (lambda: FIRE(dt_start=2.0), r"dt_min < dt_start <= dt_max"),
    (lambda: FIRE(refresh=True), r"FIRE\.refresh must be an integer >= 1"),
    (lambda: NewtonKrylov(eta_min=0.5, eta_max=0.1), r"eta_min <= eta_max"),
    (lambda: NewtonKrylov(cg_max=0), r"NewtonKrylov\.cg_max must be an integer >= 1"),
    (lambda: NewtonKrylov(warm_start=("bulge",)), r"NewtonKrylov\.warm_start must hold solvers"),
    (lambda: Engine(finish_below=0.0), r"Engine\.finish_below must be finite and > 0"),
    (lambda: Engine(newton_steps=-1), r"Engine\.newton_steps must be an integer >= 0"),
    (lambda: FixedPoint(safety=2.0), r"FixedPoint\.safety must lie in \(0, 2\)"),
    (lambda: FixedPoint(delta=-1.0), r"FixedPoint\.delta must be finite and > 0 \(or None\)"),
    (lambda: FixedPoint(step_rtol=1.5), r"FixedPoint\.step_rtol must be in \(0, 1\)"),
    (lambda: BulgePredictor(root_steps=0), r"BulgePredictor\.root_steps must be an integer"),
])
def test_bad_solver_settings_are_rejected_when_the_solver_is_made(make, match):
    """Every solver checks its settings in ``__post_init__`` (one shared check,
    `solvers.base.check_settings`): the error names the setting and its range before
    anything is traced."""
    with pytest.raises(ParameterError, match=match):
        make()


def test_valid_solver_settings_are_accepted():
    """The edges of the ranges that the solvers use (no steps at all, None for the paper's
    rule and the derived delta, NumPy scalars) are valid."""
    FIRE(max_steps=0)
    FIRE(rtol=np.float64(1e-6), max_steps=np.int64(5), f_alpha=1.0)
    FixedPoint(rtol=None, delta=None, refresh=0)
    NewtonKrylov(warm_start=None, ls_steps=0)
    Engine()
