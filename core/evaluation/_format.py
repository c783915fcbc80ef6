"""Numbers for people (the report, the summaries, the reproductions): a leaf module."""

from __future__ import annotations

from typing import SupportsFloat

import numpy as np

__all__ = ["format_number"]


_SUPERSCRIPT = str.maketrans(
    "-0123456789", "\u207b\u2070\u00b9\u00b2\u00b3\u2074\u2075\u2076\u2077\u2078\u2079"
)


def format_number(v: SupportsFloat | None) -> str:
    """A number for people: ``12,934``, ``0.5468``, ``2.99×10⁻⁵`` (never ``1.29e+04``); "" for None / NaN."""
    if v is None or not np.isfinite(float(v)):
        return ""
    v = float(v)
    if v == 0:
        return "0"
    if abs(v) >= 1000:
        return f"{v:,.0f}"
    if abs(v) >= 1e-3:
        return f"{v:.4g}"
    mantissa, exponent = f"{v:.2e}".split("e")
    mantissa = mantissa.rstrip("0").rstrip(".")
    return f"{mantissa}\u00d710{str(int(exponent)).translate(_SUPERSCRIPT)}"
