"""The installed JAX compiles the CPU programs jaxvalve relies on correctly.

jaxlib 0.10's YNNPACK fusions have miscompiled CPU programs silently (jax-ml/jax#39103, on
0.10.2) and crashed depending on the CPU (#39257): `jaxvalve.xla_setup` turns them off,
and pyproject.toml excludes 0.10.2.  These tests check both, run #39103's reproducer, and
compare the jitted force, energy and stretch check of every material with op-by-op
evaluation on the machine that runs them."""
import os
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxvalve.mechanics import assembly

from jaxvalve.geometry import meshgen

from jaxvalve import xla_setup
from jaxvalve.mechanics.materials import Gent, MassSpring, NeoHookean, StVenantKirchhoff
from jaxvalve.mechanics.problem import Params, make_problem, mmhg


def test_installed_jax_is_not_a_known_miscompiling_release():
    assert jax.__version__ not in xla_setup.MISCOMPILING_JAX


def _matvec_rows(n):
    i = jnp.arange(n, dtype=jnp.float64)
    x = jnp.stack((i, jnp.zeros_like(i), jnp.zeros_like(i)), axis=1)
    M = jnp.eye(3)
    return (lambda x: jax.vmap(lambda row: jnp.sum((M @ row) ** 2))(x)), x, np.asarray(i) ** 2


def test_importing_jaxvalve_turned_the_ynnpack_fusions_off():
    """`import jaxvalve` put the flag in XLA_FLAGS before the backend started, so a
    compiled dot-and-sum (which jaxlib 0.10 hands to YNNPACK) holds no YNNPACK fusion."""
    assert xla_setup.ynn_disabled(), os.environ.get("XLA_FLAGS")
    f, x, _ = _matvec_rows(64)
    assert "__ynn" not in jax.jit(f).lower(x).compile().as_text()


def test_configure_warns_when_the_backend_has_already_started(monkeypatch):
    """Here the backend has started, so the flag can no longer act: `configure` says so and
    leaves XLA_FLAGS alone.  JAXVALVE_ALLOW_YNN=1, or the flag named by the user, is kept
    silently."""
    jnp.zeros(1).block_until_ready()
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_use_fusion_emitters=false")
    monkeypatch.delenv("JAXVALVE_ALLOW_YNN", raising=False)
    with pytest.warns(RuntimeWarning, match="YNNPACK fusions stay on"):
        xla_setup.configure()
    assert os.environ["XLA_FLAGS"] == "--xla_cpu_use_fusion_emitters=false"
    monkeypatch.setenv("JAXVALVE_ALLOW_YNN", "1")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        xla_setup.configure()
    monkeypatch.delenv("JAXVALVE_ALLOW_YNN")
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_experimental_ynn_fusion_type=dot")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        xla_setup.configure()
    assert os.environ["XLA_FLAGS"] == "--xla_cpu_experimental_ynn_fusion_type=dot"


def test_jit_matches_op_by_op_for_a_vmapped_matvec_reduction():
    """jax-ml/jax#39103: under jit, rows past 16384 came out wrong on 0.10.2 (row 16384 gave
    16368^2 instead of 16384^2), a YNNPACK fusion (correct on 0.10.2 with the fusions off,
    and on 0.10.1).  Each row here is |M x_i|^2 = x_i . x_i, exactly."""
    f, x, exact = _matvec_rows(16385)
    np.testing.assert_array_equal(np.asarray(jax.jit(f)(x)), exact)
    np.testing.assert_array_equal(np.asarray(f(x)), exact)


@pytest.fixture(scope="module")
def bulged():
    p, t, b = meshgen.disk(5.0, 3)
    prob, ref = make_problem(p, t, fixed=b)
    x = np.asarray(meshgen.lift(p), dtype=float)
    r2 = np.sum(x[:, :2] ** 2, axis=1)
    x[:, 2] = 1.8 * (1.0 - r2 / 25.0)            # a paraboloid bulge, 1.8 mm high
    x[:, :2] *= (1.0 + 0.05 * (1.0 - r2 / 25.0))[:, None]   # with some in-plane stretch
    return prob, ref, jnp.asarray(x)     # I1 + 1/I2 - 3 from 0.027 (rim) to 0.062 (centre)


@pytest.mark.parametrize("mat,admissible", [
    (StVenantKirchhoff(1.0, 0.45), True), (NeoHookean(1 / 3), True),
    (Gent(1 / 3, 2.3), True), (Gent(1 / 3, 0.04), False), (MassSpring(0.106, 0.569, 1.2), True)],
    ids=["stvk", "nh", "gent", "gent-past-limit", "ms"])
def test_jitted_force_and_stretch_check_match_op_by_op(bulged, mat, admissible):
    """The solvers run the force and the stretch check inside one jitted loop; a compiler
    fault there would give a wrong equilibrium with a small residual.  Here the compiled
    programs agree with op-by-op evaluation to rounding, for every material, and past the
    Gent limit (where the masked energies give zero force on those triangles)."""
    prob, ref, x = bulged
    params = Params(ref=ref, material=mat, thickness=0.3, pressure=mmhg(80.0))
    r = assembly.prepare(prob, params)

    def parts(x):
        return (assembly.membrane_force(x, prob, params, r)[0],
                assembly.element_energies(x, prob, params, r),
                assembly.stretch_admissible(x, prob, params, r))

    F_jit, W_jit, ok_jit = jax.jit(parts)(x)
    with jax.disable_jit():
        F_eager, W_eager, ok_eager = parts(x)
    assert bool(ok_jit) == bool(ok_eager) == admissible
    scale = float(jnp.max(jnp.abs(F_eager)))
    assert scale > 0 and np.all(np.isfinite(np.asarray(F_jit)))
    np.testing.assert_allclose(F_jit, F_eager, rtol=0, atol=1e-12 * scale)
    finite = np.isfinite(np.asarray(W_eager))
    np.testing.assert_array_equal(np.isfinite(np.asarray(W_jit)), finite)
    np.testing.assert_allclose(np.asarray(W_jit)[finite], np.asarray(W_eager)[finite], rtol=1e-12)
    assert np.all(finite) == admissible and np.any(finite)   # past the limit: some, not all


def test_platform_summary_names_the_releases_cores_and_flags():
    """The line the test run ends with and `benchmarks/optimize_cli.py` prints."""
    import jaxlib

    line = xla_setup.platform_summary()
    assert line.startswith(f"jax {jax.__version__}, jaxlib {jaxlib.__version__}, ")
    assert f", {os.cpu_count()} cores, ISA " in line
    assert line.endswith(f"XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r}")
    assert xla_setup.NO_YNN_FLAG in line
