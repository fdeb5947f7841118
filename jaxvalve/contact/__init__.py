"""Contact between membrane bodies (leaflets): distances, pair lists, contact laws.

* `BarrierContact` - the IPC log barrier on point-triangle and edge-edge distances: smooth,
  and with every solver step filtered, leaflets never cross (`barrier`, `ipc_distance`).
* `PaperContact` - the paper's force law (2.2), as written (not differentiable).
* `pairs` - the pair lists inside jit (build, prune, update, overflow) over the broad
  phase of `grid`; `ipc_pairs` and `ccd` are their host references.
"""
from .geometry import (
    closest_point_barycentric,
    point_triangle_distance,
    point_triangle_distance_np,
    safe_norm,
    signed_plane_distance,
    triangle_normal,
)
from .barrier import BarrierContact
from .paper import PaperContact, vicinity_threshold

__all__ = [
    "closest_point_barycentric", "point_triangle_distance", "point_triangle_distance_np",
    "safe_norm", "signed_plane_distance", "triangle_normal",
    "PaperContact", "vicinity_threshold", "BarrierContact",
]
