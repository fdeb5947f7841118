"""Plain JSON data from nested results (dicts, dataclasses, tuples, numpy arrays and
scalars); NaN and inf become None.  Shared by `CoaptationResult.as_dict` and the
`metrics.json` writer."""
from __future__ import annotations

import dataclasses
import math

import numpy as np

__all__ = ["plain"]


def plain(v):
    """``v`` as JSON types: dict / list / bool / int / float / str / None."""
    if isinstance(v, dict):
        return {str(k): plain(a) for k, a in v.items()}
    if dataclasses.is_dataclass(v) and not isinstance(v, type):
        return {f.name: plain(getattr(v, f.name)) for f in dataclasses.fields(v)}
    if isinstance(v, (tuple, list)):
        return [plain(a) for a in v]
    if isinstance(v, np.ndarray):
        return plain(v.tolist())
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return float(v) if math.isfinite(v) else None
    if v is None or isinstance(v, str):
        return v
    return str(v)
