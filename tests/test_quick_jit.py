"""`quick_jit`: the same values as `jax.jit`, usable inside other transformations, and one
compilation for new values of the same shapes."""
import jax
import jax.numpy as jnp
import numpy as np

from jaxvalve.quick_jit import QUICK_CPU_OPTIONS, quick_jit


def _energy(F, mu, lam):
    """St.Venant-Kirchhoff energy density (MPa) of deformation gradients F (B, 3, 3)."""
    E = 0.5 * (jnp.swapaxes(F, -1, -2) @ F - jnp.eye(3))
    tr = jnp.trace(E, axis1=-2, axis2=-1)
    return jnp.sum(0.5 * lam * tr**2 + mu * jnp.sum(E * E, axis=(-2, -1)))


def _stress(F, mu, lam):
    return jax.grad(_energy)(F, mu, lam)


def _inputs(seed=0):
    F = jnp.eye(3) + 0.1 * jnp.asarray(np.random.default_rng(seed).normal(size=(16, 3, 3)))
    return F, jnp.asarray(0.3), jnp.asarray(1.2)


def test_quick_jit_matches_jit_and_the_analytic_stress():
    quick = quick_jit(_stress)
    F, mu, lam = _inputs()
    P = np.asarray(quick(F, mu, lam))
    np.testing.assert_allclose(P, np.asarray(jax.jit(_stress)(F, mu, lam)), rtol=0, atol=1e-14)
    # first Piola-Kirchhoff stress of StVK: P = F (2 mu E + lam tr(E) I)
    Fn = np.asarray(F)
    E = 0.5 * (np.swapaxes(Fn, -1, -2) @ Fn - np.eye(3))
    S = 2 * 0.3 * E + 1.2 * np.trace(E, axis1=-2, axis2=-1)[:, None, None] * np.eye(3)
    np.testing.assert_allclose(P, Fn @ S, rtol=1e-12, atol=1e-14)
    # at the top level on the CPU the program compiled with the options is the one run
    expect = quick._quick if jax.default_backend() == "cpu" else quick._plain
    assert quick._pick(((F, mu, lam), {})) is expect
    assert expect._cache_size() == 1
    assert QUICK_CPU_OPTIONS               # options are set, so the two jits differ


def test_quick_jit_inside_jit_grad_and_vmap():
    # compile options belong to top-level programs: traced calls use the plain jit
    quick = quick_jit(_energy)
    F, mu, lam = _inputs(1)
    picked = []
    jax.jit(lambda F: picked.append(quick._pick(((F, mu, lam), {}))) or F)(F)
    assert picked == [quick._plain]
    outer = jax.jit(lambda F, mu: quick(F, mu, lam) * 2.0)
    np.testing.assert_allclose(float(outer(F, mu)), 2.0 * float(_energy(F, mu, lam)), rtol=1e-14)
    g = jax.grad(lambda mu: quick(F, mu, lam))(mu)
    # d/dmu of sum mu |E|^2 is sum |E|^2
    Fn = np.asarray(F)
    E = 0.5 * (np.swapaxes(Fn, -1, -2) @ Fn - np.eye(3))
    np.testing.assert_allclose(float(g), float(np.sum(E * E)), rtol=1e-12)
    per = jax.vmap(lambda f: quick(f[None], mu, lam))(F)
    np.testing.assert_allclose(float(jnp.sum(per)), float(_energy(F, mu, lam)), rtol=1e-12)


def test_quick_jit_compiles_once_for_new_values():
    quick = quick_jit(_stress)
    for seed in range(3):
        F, mu, lam = _inputs(seed)
        quick(F, mu * (1 + seed), lam)
    assert quick._cache_size() == 1


def test_quick_jit_static_arguments_pass_through():
    @quick_jit(static_argnums=(1,))
    def power(x, k):
        return x**k

    x = jnp.arange(4.0)
    np.testing.assert_array_equal(np.asarray(power(x, 3)), np.arange(4.0) ** 3)
