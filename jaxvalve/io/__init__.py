"""Input and output: patient roots and surfaces through meshio (`files`, the only module
that imports meshio), 3D Slicer markups (`markups`), CT volumes and masks (`volumes`), the
outputs of a simulation (`report`: metrics.json and .vtu; `plots`: PNG figures;
`html_report`: the self-contained report.html), the segmentation's QC figure
(`qc_figure`) and plain JSON data (`jsonable`).

``from jaxvalve import io`` gives `files`' API (``io.read_root``, ...)."""
from ..lazy_exports import lazy_exports

_API = (
    'UNITS', 'LandmarksFileError', 'RootFileError', 'SurfaceFileError',
    'check_out_dir', 'read_landmarks', 'read_root', 'read_surface',
    'write_landmarks', 'write_root', 'write_surface')

__getattr__, __dir__ = lazy_exports(__name__, "files", _API)
