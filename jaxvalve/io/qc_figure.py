"""The quality-control figure of a segmentation: three orthogonal slices through the
mask's centre (the seed marked where it lies on the slice) with the mask's contour over the image, and the wall surface (with the landmarks and
suture paths, when given).  matplotlib, imported lazily."""
from __future__ import annotations

import numpy as np

__all__ = ["segmentation_figure"]


def segmentation_figure(volume, seg, surface, path=None, root=None, window=(-200, 600)):
    """Draw the figure (and save it to ``path``, PNG, when given); returns the Figure.
    volume: `jaxvalve.imaging.volume.Volume`; seg: its `Segmentation`; surface: (points
    (P, 3), triangles (T, 3)) LPS mm; root: an optional `AorticRoot` on that surface;
    window: the grey window, HU."""
    from .plots import _pyplot
    plt = _pyplot()
    fig = plt.figure(figsize=(13, 4.2))
    sp = volume.spacing
    centre = np.round(np.argwhere(seg.mask).mean(axis=0)).astype(int) if seg.mask.any() \
        else np.asarray(seg.seed)
    for ax_i in range(3):
        ax = fig.add_subplot(1, 4, ax_i + 1)
        k = int(centre[ax_i])
        img = np.take(volume.data, k, axis=ax_i)
        msk = np.take(seg.mask, k, axis=ax_i)
        rest = [a for a in range(3) if a != ax_i]
        ext = [0, img.shape[0] * sp[rest[0]], 0, img.shape[1] * sp[rest[1]]]
        ax.imshow(img.T, origin="lower", cmap="gray", vmin=window[0], vmax=window[1],
                  extent=ext, aspect="equal")
        if msk.any():
            ax.contour(np.linspace(ext[0], ext[1], img.shape[0]),
                       np.linspace(ext[2], ext[3], img.shape[1]), msk.T.astype(float),
                       levels=[0.5], colors="tab:red", linewidths=1.0)
        if int(seg.seed[ax_i]) == k:
            ax.plot(*[seg.seed[a] * sp[a] for a in rest], "+", color="yellow", ms=10)
        ax.set_title(f"slice {k} of index axis {ax_i} (through the mask's centre)", fontsize=8)
        ax.set_xlabel(f"index axis {rest[0]} (mm)", fontsize=8)
        ax.set_ylabel(f"index axis {rest[1]} (mm)", fontsize=8)
        ax.tick_params(labelsize=7)
    ax = fig.add_subplot(1, 4, 4, projection="3d")
    P, T = np.asarray(surface[0]), np.asarray(surface[1])
    step = max(1, len(T) // 6000)
    ax.plot_trisurf(P[:, 0], P[:, 1], P[:, 2], triangles=T[::step], color="0.8",
                    alpha=0.35, linewidth=0)
    if root is not None:
        c = root.commissures
        ax.scatter(c[:, 0], c[:, 1], c[:, 2], color="tab:red", s=20)
        for i, p in enumerate(root.paths):
            ax.plot(p[:, 0], p[:, 1], p[:, 2], color=("tab:blue", "tab:orange",
                                                      "tab:green")[i], lw=2)
    lo, hi = P.min(axis=0), P.max(axis=0)
    mid, half = 0.5 * (lo + hi), 0.5 * float(np.max(hi - lo))
    for set_lim, m in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), mid):
        set_lim(m - half, m + half)
    ax.set_title("wall surface (LPS mm)" + (", landmarks" if root is not None else ""),
                 fontsize=9)
    ax.tick_params(labelsize=6)
    fig.tight_layout()
    if path is not None:
        fig.savefig(path, dpi=110)
    return fig
