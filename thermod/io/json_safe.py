"""Plain JSON values from thermod's data: numpy scalars and arrays unwrapped, non-finite floats as null,
objects with ``as_dict()`` expanded. Every JSON thermod writes (wire headers, report.json, the web view)
goes through `jsonable`, so each parses with strict JSON readers.
"""

from __future__ import annotations

import math

import numpy as np


def jsonable(x):
    """Plain JSON types; non-finite floats become null so non-Python parsers accept the header."""
    t = type(x)
    if t is str or t is int or t is bool or x is None:     # the common leaves first: headers are hot
        return x
    if t is float:
        return x if math.isfinite(x) else None
    if t is dict:
        return {k if type(k) is str else str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return jsonable(x.tolist())
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, (int, np.integer)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        x = float(x)
        return x if math.isfinite(x) else None
    if x is None or isinstance(x, str):
        return x
    if hasattr(x, "as_dict"):
        return jsonable(x.as_dict())
    raise TypeError(f"header value of type {type(x).__name__} is not JSON-serialisable")
