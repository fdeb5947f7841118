"""The valve: three leaflets placed in the root (`placement`), stacked into one problem
and closed under pressure (`model`: `build_valve`, `settle`, `close`), the one closure
driver of every caller (`closure`), the state checks of a closed valve (`checks`,
`intersect`: folds, collapsed triangles, crossing leaflets) and the template-to-valve map
that gradients in r, a and b go through (`design`).

``from jaxvalve import valve`` gives `model`'s API (``valve.build_valve``, ...)."""
from ..lazy_exports import lazy_exports

_API = (
    'STATE_FAILURES', 'Valve', 'ValveSolution', 'build_valve', 'checked', 'close',
    'commissure_groups', 'leaflet_crossings', 'settle', 'state_failure')

__getattr__, __dir__ = lazy_exports(__name__, "model", _API)
