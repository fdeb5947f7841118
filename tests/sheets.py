"""Small sheet meshes shared by the contact tests."""
import numpy as np


def grid_sheet(n, L, z=0.0, origin=(0.0, 0.0), jitter=0.0, rng=None, flip=False):
    """Square sheet [0,L]^2 at height z, n x n cells, 2 triangles each; normal +z
    (or -z when flip)."""
    xs = np.linspace(0.0, L, n + 1)
    X, Y = np.meshgrid(xs, xs, indexing="ij")
    p = np.stack([X.ravel() + origin[0], Y.ravel() + origin[1], np.full(X.size, z)], 1)
    if jitter:
        p += jitter * (L / n) * rng.uniform(-1, 1, p.shape)
    t = []
    for i in range(n):
        for j in range(n):
            a = i * (n + 1) + j
            b = a + n + 1
            t += [[a, b, b + 1], [a, b + 1, a + 1]]
    t = np.array(t, dtype=np.int32)
    if flip:
        t = t[:, [0, 2, 1]]
    # (x, y, z) with b along +x then +y: (b-a) x (b+1-a) = +x cross (+x+y) = +z
    return p, t


def combine(*sheets):
    """Stack sheets (points, triangles) into one mesh; body id = sheet index."""
    xs, ts, bs, off = [], [], [], 0
    for k, (p, t) in enumerate(sheets):
        xs.append(p)
        ts.append(t + off)
        bs.append(np.full(len(p), k, np.int32))
        off += len(p)
    return np.concatenate(xs), np.concatenate(ts).astype(np.int32), np.concatenate(bs)
