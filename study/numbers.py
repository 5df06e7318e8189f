"""How study/ rounds the numbers it stores and writes them in tables: one rule each.

`rounded` is what goes into result JSON (4 decimals unless a caller asks otherwise; None for a
missing, NaN or infinite value, which JSON cannot hold); `number_text` and `interval_text` are what
text tables and reports print.
"""

from __future__ import annotations

import math
import numbers


def rounded(v, digits: int = 4) -> float | None:
    """`v` as a float rounded to `digits` decimals; None when `v` is None, NaN or infinite."""
    if v is None or not math.isfinite(float(v)):
        return None
    return round(float(v), digits)


def significant(v, digits: int = 3) -> float | None:
    """`v` kept to `digits` significant figures (a ratio or a time whose size varies by orders of
    magnitude between machines: 0.0641 and 1.93 both keep their three figures, where a fixed two
    decimals would move 0.0641 by 6 %); None when `v` is None, NaN or infinite."""
    if v is None or not math.isfinite(float(v)):
        return None
    return float(f"{float(v):.{digits}g}")


def rounded_interval(iv, digits: int = 4) -> list | None:
    """An interval (lo, hi) as [rounded(lo), rounded(hi)]; None stays None."""
    return None if iv is None else [rounded(iv[0], digits), rounded(iv[1], digits)]


def number_text(v) -> str:
    """A table cell: "-" for None; a float with 3 decimals, none from 1000 up, and in scientific
    notation under 0.01 (so a small squared error keeps its magnitude); anything else as str()."""
    if v is None:
        return "-"
    if isinstance(v, numbers.Integral) or not isinstance(v, numbers.Real):
        return str(v)
    v = float(v)
    if v != 0 and abs(v) < 0.01:
        return f"{v:.1e}"
    return f"{v:.0f}" if abs(v) >= 1000 else f"{v:.3f}"


def interval_text(iv, signed: bool = False) -> str:
    """"[lo, hi]" with `number_text`'s cells, or "-" for None; `signed`: both ends with their sign
    and 3 decimals (a difference: "[+0.012, -0.004]")."""
    if iv is None:
        return "-"
    if signed:
        return f"[{iv[0] + 0.0:+.3f}, {iv[1] + 0.0:+.3f}]"  # + 0.0: a negated 0 prints as +0.000
    return f"[{number_text(iv[0])}, {number_text(iv[1])}]"
