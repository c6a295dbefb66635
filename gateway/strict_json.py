"""Values for strict JSON (``allow_nan=False``): one place that says how a missing number is written."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any


def nan_to_none(x: Any) -> Any:
    """``x`` with every NaN or infinite float as ``None`` (JSON's missing number).

    Recurses into mappings (a ``MappingProxyType`` too, returned as dicts), lists and tuples (returned as
    lists); anything else is returned as it is.
    """
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, Mapping):
        return {k: nan_to_none(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [nan_to_none(v) for v in x]
    return x
