"""Rounding for truth.json: compact, stable numbers."""

from __future__ import annotations

from typing import Any

import numpy as np


def round_json(x: Any, digits: int = 6) -> Any:
    """Round floats (in lists and dicts too) for a compact, stable JSON."""
    if isinstance(x, dict):
        return {k: round_json(v, digits) for k, v in x.items()}
    if isinstance(x, np.ndarray):
        return [round_json(v, digits) for v in x.tolist()]
    if isinstance(x, list | tuple):
        return [round_json(v, digits) for v in x]
    if isinstance(x, float | np.floating):
        return round(float(x), digits)
    if isinstance(x, np.integer):
        return int(x)
    return x
