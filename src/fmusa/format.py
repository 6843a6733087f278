"""Numbers and tables as the reports print them."""
from __future__ import annotations

import math


def fmt(x: float, sig: int = 3, strip: bool = True, plain_min: float = 1e-2) -> str:
    """A compact number: ``1.56e4``, ``2.63e-2``, ``0.656``, ``412``, ``822067.3``; "–" for NaN.

    Numbers from ``plain_min`` up to 10**max(3, sig) are written plainly with ``sig`` significant digits
    (so ``fmt(822067.26, 7)`` is ``822067.3``), others as mantissa e exponent; ``strip`` drops trailing
    zeros of the mantissa (``5e-4`` rather than ``5.00e-4``)."""
    if x is None:
        return "–"
    try:
        x = float(x)
    except (TypeError, ValueError):
        return str(x)
    if math.isnan(x):
        return "–"
    if math.isinf(x):
        return "∞" if x > 0 else "−∞"
    if x == 0:
        return "0"
    ax = abs(x)
    if plain_min <= ax < 10 ** max(3, sig):
        return f"{x:.{sig}g}"
    e = int(math.floor(math.log10(ax)))
    m = x / 10 ** e
    if round(abs(m), sig - 1) >= 10:
        e += 1
        m = x / 10 ** e
    ms = f"{m:.{max(sig - 1, 0)}f}"
    if strip and "." in ms:
        ms = ms.rstrip("0").rstrip(".")
    return f"{ms}e{e}"

