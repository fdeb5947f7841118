"""One-sided smooth contact: the gap is signed by the side of the nearest triangle."""
import jax
import jax.numpy as jnp
import numpy as np

from jaxvalve import contact as C


def _scene(z):
    """A unit-square sheet (body 0, normal +z) and one triangle of body 1 whose first node
    sits at height z over the sheet's centre."""
    sheet = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0.0]])
    probe = np.array([[0.3, -0.2, z], [5, 0, z], [5, 1, z]])
    x = jnp.asarray(np.concatenate([sheet, probe]))
    tri = jnp.asarray([[0, 1, 2], [0, 2, 3], [4, 6, 5]])
    body = jnp.asarray([0, 0, 0, 0, 1, 1, 1])
    nb = C.build_neighbours_checked(x, tri, body, cutoff=1.5)
    area = jnp.asarray([1.0, 1, 1, 1, 1, 1, 1])
    return x, tri, nb, area


def test_crossed_node_is_pushed_back_to_the_positive_side():
    law = C.SmoothContact(stiffness=1.0, gap=0.2, one_sided=True)
    for z, up in [(0.1, True), (-0.1, True), (-0.5, True)]:
        x, tri, nb, area = _scene(z)
        f = law.forces(x, tri, nb, area)
        assert float(f[4, 2]) > 0  # toward +n of the sheet, whichever side it is on
    # the unsigned law pushes a crossed node further through
    x, tri, nb, area = _scene(-0.1)
    f = C.SmoothContact(stiffness=1.0, gap=0.2).forces(x, tri, nb, area)
    assert float(f[4, 2]) < 0


def test_one_sided_energy_is_continuous_through_the_sheet_and_matches_the_formula():
    law = C.SmoothContact(stiffness=2.0, gap=0.2, one_sided=True)
    zs = np.array([-0.3, -1e-9, 0.0, 1e-9, 0.1, 0.25])
    e = []
    for z in zs:
        x, tri, nb, area = _scene(z)
        e.append(float(law.energy(x, tri, nb, area)))
    # node 4 (area 1) over the sheet: 0.5 * a * (k/2) (g0 - s)_+^2, s = z
    expected = 0.5 * 1.0 * 0.5 * 2.0 * np.maximum(0.2 - zs, 0) ** 2
    np.testing.assert_allclose(e, expected, atol=1e-12)
    x, tri, nb, area = _scene(-0.05)
    g = jax.grad(law.energy)(x, tri, nb, area)
    assert np.all(np.isfinite(np.asarray(g)))
