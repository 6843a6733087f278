"""Numbers and tables as the reports print them."""
from __future__ import annotations

import math
import re


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



#: Characters that Markdown gives a meaning anywhere in a line: escaped with a backslash by :func:`md_text`
#: (``(`` and ``!`` make a link or an image only next to a ``[``, which is escaped).
_MD_SPECIAL = set("\\`*_[]~")
#: HTML's and the table's characters, as entities (a backslash would not stop a ``|`` in every renderer)
_HTML = {"<": "&lt;", ">": "&gt;", "&": "&amp;", "|": "&#124;"}
#: A line that starts like a heading, a list, a quote or a rule
_BLOCK_START = re.compile(r"^(?:[#+=>-]|\d+[.)])")


def printable(text: object) -> str:
    """``text`` with control characters (terminal escapes, NUL, line breaks) shown as ``\\xNN``: text an
    FMU or a data file supplies, printed to a terminal."""
    return "".join(ch if ch.isprintable() or ch == " " else f"\\x{ord(ch):02x}" if ord(ch) < 256
                   else f"\\u{ord(ch):04x}" for ch in str(text))


def md_text(text: object) -> str:
    """``text`` as literal Markdown on one line: what an FMU or a data file supplies (a description, a unit, a
    log message, a column name) shows as written and never becomes a link, a table cell, markup or HTML
    (``<script>`` stays text, ``|`` stays in its cell)."""
    s = " ".join(printable(str(text).replace("\r", " ").replace("\n", " ").replace("\t", " ")).split())
    out = "".join(_HTML.get(ch) or ("\\" + ch if ch in _MD_SPECIAL else ch) for ch in s)
    m = _BLOCK_START.match(out)
    if m is None:
        return out
    k = m.end() - 1          # the character that makes the block: escaped (``\\- item``, ``1\\. item``)
    return out[:k] + "\\" + out[k:]


def md_code(text: object) -> str:
    """``text`` as an inline code span that no backtick in it can close; HTML entities (``<``, ``&``) in a
    code span are shown literally by every Markdown renderer (a table escapes its ``|``)."""
    s = " ".join(printable(str(text)).split())
    longest, cur = 0, 0
    for ch in s:
        cur = cur + 1 if ch == "`" else 0
        longest = max(longest, cur)
    fence = "`" * (longest + 1)
    pad = " " if s.startswith("`") or s.endswith("`") or not s else ""
    return f"{fence}{pad}{s}{pad}{fence}" if s else "` `"
