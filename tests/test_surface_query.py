"""The exact closest-point query on a triangle surface (`jaxvalve.geometry.surface_query`)."""
import numpy as np
import pytest

from jaxvalve.contact.geometry import point_triangle_distance_np as ptd
from jaxvalve.errors import MeshError
from jaxvalve.geometry.surface_query import SurfaceIndex, closest_points, project_to_surface


def _plane(n=21, step=0.5):
    g = np.arange(n) * step
    X, Y = np.meshgrid(g, g, indexing="ij")
    P = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], 1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = (idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(),
                  idx[:-1, 1:].ravel())
    return P, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def test_closest_points_on_a_plane_are_the_orthogonal_feet_or_the_border():
    P, T = _plane()
    q = np.array([[3.3, 4.1, 2.5], [5.0, 5.0, -1.0], [12.0, 5.0, 0.0], [-3.0, -4.0, 0.0]])
    d, x, _ = closest_points(q, P, T)
    np.testing.assert_allclose(d, [2.5, 1.0, 2.0, 5.0], atol=1e-12)
    np.testing.assert_allclose(x, [[3.3, 4.1, 0], [5, 5, 0], [10, 5, 0], [0, 0, 0]],
                               atol=1e-12)


@pytest.mark.parametrize("k", [1, 8])
def test_closest_points_match_brute_force_on_a_curved_uneven_mesh(k):
    # a bumpy half-cylinder with triangles of very different sizes: k = 1 candidate forces
    # the exact fallback (the nearest centroid is often not the closest triangle)
    rng = np.random.default_rng(3)
    th = np.sort(np.concatenate([[0, np.pi], rng.uniform(0, np.pi, 30)]))
    z = np.sort(np.concatenate([[0, 10], rng.uniform(0, 10, 12)]))
    TH, Z = np.meshgrid(th, z, indexing="ij")
    R = 5 + 0.5 * np.sin(3 * TH) * np.cos(Z)
    P = np.stack([R * np.cos(TH), R * np.sin(TH), Z], -1).reshape(-1, 3)
    n, m = len(th), len(z)
    idx = np.arange(n * m).reshape(n, m)
    a, b, c, d = (idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(),
                  idx[:-1, 1:].ravel())
    T = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    q = rng.uniform([-8, -2, -2], [8, 8, 12], size=(200, 3))
    d, x, t = SurfaceIndex(P, T).closest(q, k=k)
    brute = np.array([ptd(np.repeat(p[None], len(T), 0), P[T[:, 0]], P[T[:, 1]],
                          P[T[:, 2]]).min() for p in q])
    np.testing.assert_allclose(d, brute, rtol=1e-12, atol=1e-12)
    # the closest point lies on its triangle, at the reported distance
    np.testing.assert_allclose(np.linalg.norm(q - x, axis=1), d, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(ptd(x, P[T[t, 0]], P[T[t, 1]], P[T[t, 2]]), 0, atol=1e-9)


def test_projection_is_idempotent_and_refuses_bad_input():
    P, T = _plane()
    q = np.array([[1.1, 2.2, 3.0], [9.9, 0.3, -0.2]])
    x, moved = project_to_surface(q, P, T)
    np.testing.assert_allclose(moved, [3.0, 0.2], atol=1e-12)
    x2, moved2 = project_to_surface(x, P, T)
    np.testing.assert_allclose(x2, x, atol=1e-12)
    assert moved2.max() < 1e-12
    with pytest.raises(MeshError, match="NaN"):
        closest_points([[np.nan, 0, 0]], P, T)
    with pytest.raises(MeshError, match="indices"):
        closest_points(q, P, T + len(P))
