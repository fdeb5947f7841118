"""Soft-min contact distance (`SmoothContact(soft_min=True)`, `smooth.soft_distance`):
exact where candidates tie, smooth where the nearest triangle switches, bounded by and
tending to the hard minimum, with consistent, balanced forces."""
import math

import numpy as np
import pytest
import jax
import jax.numpy as jnp

from jaxvalve.contact import SmoothContact, build_neighbours_checked, node_areas
from jaxvalve.contact.smooth import nearest_triangles, soft_distance
from jaxvalve.errors import ParameterError
from sheets import combine, grid_sheet


# ------------------------------------------------------------------------ helpers
def lone_node(p):
    return np.asarray([p], float), np.zeros((0, 3), np.int32)


def crumpled(seed, n=5, L=2.5):
    rng = np.random.default_rng(seed)
    sheets = []
    for k in range(2):
        p, t = grid_sheet(n, L, z=0.15 * k)
        p += 0.2 * (L / n) * rng.uniform(-1, 1, p.shape)
        p[:, 2] += 0.3 * np.sin(1.3 * p[:, 0] + k) * np.cos(0.9 * p[:, 1])
        p[:, 2] += 0.05 * rng.standard_normal(len(p))
        sheets.append((p, t))
    return sheets


D_TIE = 0.1       # distance of the parallel sheets
Z_CREASE = 0.15   # height of the node over the crease
SPACING = 10.0    # the scenes lie this far apart (mm): no candidates between them


def _shift(sheet, k):
    p, t = sheet
    return p + np.array([SPACING * k, 0.0, 0.0]), t


def _v_shape():
    """Two triangles with faces z = |x|, meeting along the y axis, normals up."""
    v = np.array([[0.0, -2.0, 0.0], [0.0, 2.0, 0.0], [-2.0, 0.0, 2.0], [2.0, 0.0, 2.0]])
    return v, np.array([[0, 1, 2], [1, 0, 3]], np.int32)  # normals (1, 0, 1), (-1, 0, 1)


# Every scene in one mesh, so that the neighbour list, the distances, the energies and
# their gradients compile once (compile time dominates); a scene is selected by masking
# the node areas (a group carries the area of its node) and by its bodies.
SCENES = {
    # lower h = 1, upper h = 0.5 at D_TIE: ties (upper nodes over vertices, edge and
    # diagonal midpoints of the lower sheet; lower nodes over upper vertices)
    "tie": (0, [grid_sheet(3, 3.0), grid_sheet(6, 3.0, z=D_TIE)]),
    "fine": (1, [grid_sheet(4, 2.0), grid_sheet(8, 2.0, z=D_TIE)]),   # h = 0.5 / 0.25
    "crease": (2, [_v_shape(), lone_node([0.0, 0.0, Z_CREASE])]),
    "crumpled": (3, crumpled(5)),
    "sheet": (4, [grid_sheet(4, 2.0), lone_node([0.7, 0.9, 0.05])]),  # normal +z
}


class World:
    def __init__(self):
        sheets, self.bodies, b = [], {}, 0
        for name, (k, parts) in SCENES.items():
            sheets += [_shift(s, k) for s in parts]
            self.bodies[name] = list(range(b, b + len(parts)))
            b += len(parts)
        x, tri, body = combine(*sheets)
        self.nbrs = build_neighbours_checked(x, tri, body, 0.45)
        self.x, self.tri, self.body = jnp.asarray(x), jnp.asarray(tri), body
        self.area = node_areas(self.x, self.tri)

    def nodes(self, name):
        return np.isin(self.body, self.bodies[name])

    def area_of(self, name, lone=None):
        """Node areas of scene ``name`` only (lone: that node gets area 1)."""
        a = jnp.where(jnp.asarray(self.nodes(name)), self.area, 0.0)
        return a if lone is None else a.at[lone].set(1.0)

    def groups(self, name):
        """Groups (R,) whose node lies in scene ``name``."""
        n = self.x.shape[0]
        gn = np.asarray(self.nbrs.group_node)
        return (gn < n) & self.nodes(name)[np.minimum(gn, n - 1)]

    def lone(self, name):
        return int(np.nonzero(self.nodes(name))[0][-1])


@pytest.fixture(scope="module")
def world():
    return World()


@jax.jit
def _soft_and_hard(x, tri, nbrs, tau):
    """(soft distance, hard (nearest) distance, found) per group; tau traced."""
    _, _, found, dist = nearest_triangles(x, tri, nbrs)
    return soft_distance(x, tri, nbrs, found, softness=tau), dist, found


def soft_and_hard(w, name, tau):
    s, hard, found = (np.asarray(a) for a in _soft_and_hard(w.x, w.tri,
                                                             w.nbrs, tau))
    g = w.groups(name)
    assert np.all(found[g])                          # every node there sees the other body
    return s[g], hard[g]


# energy and gradient in one compilation per law (the soft law compiles in seconds)
_value_and_grad = jax.jit(jax.value_and_grad(
    lambda x, c, tri, nbrs, area: c.energy(x, tri, nbrs, area)))


def _energy(c, x, tri, nbrs, area):
    return _value_and_grad(x, c, tri, nbrs, area)[0]


def _grad(x, c, tri, nbrs, area):
    return _value_and_grad(x, c, tri, nbrs, area)[1]


def soft(**kw):
    return SmoothContact(soft_min=True, **kw)


# ------------------------------------------------------------------------ ties
def test_parallel_sheets_ties_are_exact_and_energy_equals_hard_min(world):
    """The triangles holding the foot point tie exactly; the others lie >= 0.35 mm aside,
    so >= 0.25 mm farther, and with softness 0.005 their weight is < 1e-21: the soft
    distance is d to ~1e-12 at every node and the energy is the hard-min energy."""
    w, d = world, D_TIE
    s, hard = soft_and_hard(w, "tie", 0.005)
    assert len(s) == 16 + 49
    assert np.max(np.abs(hard - d)) < 1e-12
    assert np.max(np.abs(s - d)) < 1e-12
    area = w.area_of("tie")
    for k, g0 in ((1.0, 0.2), (2.5, 0.15)):
        e_soft = float(_energy(soft(stiffness=k, gap=g0, softness=0.005), w.x, w.tri, w.nbrs,
                               area))
        e_hard = float(_energy(SmoothContact(stiffness=k, gap=g0), w.x, w.tri, w.nbrs, area))
        # 1/2 (both directions) x (k/2)(g0 - d)^2 x (area of both sheets)
        assert e_hard == pytest.approx(0.5 * 0.5 * k * (g0 - d) ** 2 * 18.0, rel=1e-12)
        assert abs(e_soft - e_hard) < 1e-10 * e_hard
    F_s = -np.asarray(_grad(w.x, soft(softness=0.005), w.tri, w.nbrs, area))
    F_h = -np.asarray(_grad(w.x, SmoothContact(), w.tri, w.nbrs, area))
    assert np.max(np.abs(F_s - F_h)) < 1e-10 * np.max(np.abs(F_h))
    up = w.body == w.bodies["tie"][1]        # the resultant on a sheet: k (g0 - d) x area
    assert F_s[up, 2].sum() == pytest.approx((0.2 - d) * 9.0, rel=1e-10)
    assert np.max(np.abs(F_s[:, :2])) < 1e-12


def test_default_softness_excess_over_a_flat_sheet_is_at_most_softness_over_e(world):
    """With the default softness 0.01 mm on finer sheets (h = 0.5 / 0.25) the non-tied
    neighbours count: the excess d_soft - d is >= 0 and at most ~softness / e (module
    docstring)."""
    tau = 0.01
    s, _ = soft_and_hard(world, "fine", tau)
    ex = s - D_TIE
    assert ex.min() > -1e-14
    assert 1e-8 < ex.max() <= tau / math.e


# ------------------------------------------------------------------------ crease
def test_node_over_a_concave_crease_soft_distance_and_smooth_force(world):
    """A node over the crease of a V (faces z = |x|): on the bisector both faces are at
    z0 / sqrt(2), and so is the soft distance.  Across the bisector the hard minimum
    switches face and its force jumps sideways by (1/2) a k (g0 - d) sqrt(2); the soft
    force is smooth: its jump over [-eps, eps] is O(eps / softness)."""
    w = world
    z0 = Z_CREASE
    node = w.lone("crease")
    area = w.area_of("crease", lone=node)
    s, hard = soft_and_hard(w, "crease", 0.01)
    assert len(s) == 1
    assert s[0] == pytest.approx(z0 / math.sqrt(2), abs=1e-15)          # the equal distance
    assert hard[0] == pytest.approx(z0 / math.sqrt(2), rel=1e-12)

    c_soft, c_hard = soft(softness=0.01), SmoothContact()
    x0 = float(w.x[node, 0])
    diffs = []
    for eps in (1e-3, 1e-5, 1e-7):
        jump = 0.5 * (0.2 - (z0 - eps) / math.sqrt(2)) * math.sqrt(2)
        gs, gh = [], []
        for sgn in (1, -1):
            y = w.x.at[node, 0].set(x0 + sgn * eps)
            gs.append(np.asarray(_grad(y, c_soft, w.tri, w.nbrs, area))[node])
            gh.append(np.asarray(_grad(y, c_hard, w.tri, w.nbrs, area))[node])
        assert np.linalg.norm(gh[0] - gh[1]) == pytest.approx(jump, rel=1e-9)
        diffs.append(np.linalg.norm(gs[0] - gs[1]))
        assert diffs[-1] < 10 * eps / 0.01 * jump
    # linear in eps (a continuous, differentiable force): -> 0 with eps
    assert diffs[1] / diffs[0] == pytest.approx(1e-2, rel=0.05)
    assert diffs[2] / diffs[1] == pytest.approx(1e-2, rel=0.05)
    assert diffs[2] < 1e-4 * jump
    # on the bisector the soft force has no sideways component and pushes the node up
    g0 = np.asarray(_grad(w.x, c_soft, w.tri, w.nbrs, area))[node]
    assert abs(g0[0]) < 1e-14 and g0[2] < 0


# ------------------------------------------------------------------------ generic
def test_soft_distance_bounds_and_tends_monotonically_to_the_hard_minimum(world):
    prev = None
    gaps = []
    for tau in (1e-2, 1e-3, 1e-4):
        s, hard = soft_and_hard(world, "crumpled", tau)
        assert len(s) > 20
        assert np.all(s >= hard - 1e-12 * (1 + hard))
        if prev is not None:
            assert np.all(s <= prev + 1e-15)               # d d_soft / d tau = Var / tau^2 >= 0
        prev = s
        gaps.append(np.max(s - hard))
    assert gaps[0] > gaps[1] > gaps[2]
    assert gaps[0] > 1e-4 and gaps[2] < 1e-4 / math.e * 8     # <= (#candidates) tau / e


@pytest.mark.parametrize("one_sided", [False, True])
def test_soft_energy_gradient_matches_finite_differences_and_forces_balance(world, one_sided):
    w = world
    area = w.area_of("crumpled")
    c = soft(stiffness=2.0, gap=0.2, softness=0.01, one_sided=one_sided)
    s, hard = soft_and_hard(w, "crumpled", 0.01)
    assert np.sum(hard < 0.2) >= 5                          # several active contacts
    E = float(_energy(c, w.x, w.tri, w.nbrs, area))
    g = np.asarray(_grad(w.x, c, w.tri, w.nbrs, area))
    assert E > 0 and np.max(np.abs(g)) > 1e-3
    x = np.asarray(w.x)
    h = 1e-6
    act = np.nonzero(np.any(g != 0, axis=1))[0]              # nodes that feel contact
    assert len(act) > 10 and np.all(w.nodes("crumpled")[act])
    # every coordinate of the 8 most loaded nodes and of 8 others
    big = act[np.argsort(-np.abs(g[act]).max(1))]
    act = np.concatenate([big[:8], np.random.default_rng(1).choice(big[8:], 8, replace=False)])
    fd = np.zeros((len(act), 3))
    for r, a in enumerate(act):
        for k in range(3):
            e = np.zeros_like(x)
            e[a, k] = h
            fd[r, k] = (float(_energy(c, x + e, w.tri, w.nbrs, area))
                        - float(_energy(c, x - e, w.tri, w.nbrs, area))) / (2 * h)
    assert np.max(np.abs(fd - g[act])) < 1e-6 * np.max(np.abs(g))
    v = np.random.default_rng(0).normal(size=x.shape)            # and in a random direction
    dd = (float(_energy(c, x + h * v, w.tri, w.nbrs, area))
          - float(_energy(c, x - h * v, w.tri, w.nbrs, area))) / (2 * h)
    assert abs(dd - np.sum(g * v)) < 1e-6 * np.sum(np.abs(g * v))
    F = -g
    scale = np.sum(np.abs(F))
    assert np.max(np.abs(F.sum(0))) < 1e-12 * scale                     # Newton's third law
    xc = x - x[act].mean(0)                                   # torque about the scene
    assert np.max(np.abs(np.cross(xc, F).sum(0))) < 1e-12 * scale


# ------------------------------------------------------------------------ one-sided
def test_one_sided_soft_pushes_a_crossed_node_back(world):
    """A node under a sheet (on its -n side, over a face) is pushed back toward +n by the
    one-sided soft law, with (1/2) a k (g0 + |z|) (a lone node feels half of the pair
    pressure); the unsigned soft law pushes it further through."""
    w = world
    node = w.lone("sheet")
    area = w.area_of("sheet", lone=node)
    one, two = soft(one_sided=True, softness=0.002), soft(softness=0.002)
    for z in (0.05, -0.02, -0.1):
        y = w.x.at[node, 2].set(z)
        f1 = -np.asarray(_grad(y, one, w.tri, w.nbrs, area))[node]
        assert f1[2] > 0
        assert f1[2] == pytest.approx(0.5 * (0.2 - z), rel=1e-5)
        # neighbours of the face below blend in with weights exp(-(s_T - s) / softness):
        # a small tangential part, far below the normal force
        assert np.max(np.abs(f1[:2])) < 1e-4 * f1[2]
        f2 = -np.asarray(_grad(y, two, w.tri, w.nbrs, area))[node]
        assert (f2[2] < 0) if z < 0 else (f2[2] > 0)


# ------------------------------------------------------------------------ validation
@pytest.mark.parametrize("tau", [0.0, -0.01, 0.1, 0.5, float("nan"), float("inf")])
def test_soft_min_validate_rejects_bad_softness(tau):
    with pytest.raises(ParameterError, match="softness"):
        SmoothContact(soft_min=True, softness=tau).validate()
    SmoothContact(soft_min=False, softness=tau).validate()   # unused by the hard law


def test_soft_min_validate_accepts_defaults():
    SmoothContact(soft_min=True).validate()
    SmoothContact(soft_min=True, softness=0.0999).validate()


def test_nearest_search_in_float32_finds_the_float64_triangles(world):
    """The search packs its squared distances into 64-bit keys; a float32 state is widened
    exactly, so it finds the same nearest triangles at float32 distances."""
    t64, s64, f64, d64 = (np.asarray(a) for a in nearest_triangles(world.x, world.tri,
                                                                    world.nbrs))
    x32 = world.x.astype(jnp.float32)
    t32, s32, f32, d32 = nearest_triangles(x32, world.tri, world.nbrs)
    assert d32.dtype == jnp.float32 and s32.dtype == jnp.float32
    t32, s32, f32, d32 = (np.asarray(a) for a in (t32, s32, f32, d32))
    np.testing.assert_array_equal(f32, f64)
    assert f64.sum() > 20
    np.testing.assert_allclose(d32[f64], d64[f64], rtol=1e-5, atol=1e-6)
    # ties (parallel sheets, creases) may go to another triangle at the same distance
    same = t32[f64] == t64[f64]
    assert same.mean() > 0.9
