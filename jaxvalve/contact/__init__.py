"""Contact between membrane bodies (leaflets): geometry, broad phase, contact laws.

* `SmoothContact` - the differentiable default: C1 penalty energy on node-to-surface
  distance (pressure k (g0 - d)_+, g0 = 0.2 mm, k = 1 MPa/mm).
* `PaperContact` - the paper's force law (2.2), as written (not differentiable).
* `BarrierContact` - IPC log barrier on point-triangle and edge-edge distances: smooth,
  and with CCD-filtered steps (`ccd`) leaflets never cross; its pair lists are built on
  the host (`ipc_pairs`).
* `build_neighbours` / `update` / `check_overflow` - fixed-capacity cell-grid broad phase.
"""
from .geometry import (
    closest_point_barycentric,
    point_triangle_distance,
    point_triangle_distance_np,
    safe_norm,
    signed_plane_distance,
    triangle_normal,
)
from .neighbours import (
    DEFAULT_CELL_CAPACITY,
    NeighbourList,
    brute_force_pairs,
    build_neighbours,
    build_neighbours_checked,
    check_overflow,
    default_capacity,
    needs_rebuild,
    stale_list,
    triangle_body,
    update,
)
from .barrier import BarrierContact
from .paper import PaperContact, vicinity_threshold
from .smooth import SmoothContact, node_areas, pair_distances

__all__ = [
    "closest_point_barycentric", "point_triangle_distance", "point_triangle_distance_np",
    "safe_norm", "signed_plane_distance", "triangle_normal",
    "DEFAULT_CELL_CAPACITY", "NeighbourList", "brute_force_pairs", "build_neighbours",
    "build_neighbours_checked", "check_overflow", "default_capacity", "needs_rebuild", "stale_list",
    "triangle_body", "update",
    "PaperContact", "vicinity_threshold", "BarrierContact",
    "SmoothContact", "node_areas", "pair_distances",
]
