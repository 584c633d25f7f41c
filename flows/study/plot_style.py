"""What every study figure shares: matplotlib without a display (Agg, set before pyplot is imported) and
the y range of a success axis."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

__all__ = ["plt", "y_range"]


def y_range(shown: list[float]) -> tuple[float, float]:
    """The curves' y range: what is drawn (means, intervals, run points) with 5 points of margin, within
    0-100, and at least 20 points tall (centred on what is drawn, kept inside 0-100)."""
    low, high = max(0.0, min(shown, default=0) - 5), min(100.0, max(shown, default=100) + 5)
    if high - low < 20:
        middle = min(max((low + high) / 2, 10.0), 90.0)
        low, high = middle - 10, middle + 10
    return low, high
