"""Markdown pieces the generated pages share: numbers, tables, and a block between two marker comments."""
from __future__ import annotations

from typing import Any, Sequence


def num(value: Any, digits: int = 2, unit: str = "") -> str:
    """A figure as text: fixed digits for floats, '-' for a missing one (so a table never shows None or nan)."""
    if value is None or (isinstance(value, float) and value != value):
        return "-"
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return str(value)
    text = f"{value:.{digits}f}" if isinstance(value, float) else str(value)
    return f"{text} {unit}".rstrip() if unit else text


def table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A GitHub markdown table (cells are str()-ed; pipes inside cells escaped)."""
    def line(cells: Sequence[Any]) -> str:
        return "| " + " | ".join(str(c).replace("|", "\\|") for c in cells) + " |"

    return "\n".join([line(header), line(["---"] * len(header)), *(line(r) for r in rows)])


def replace_between(text: str, begin: str, end: str, block: str) -> str:
    """`text` with what lies between the `begin` and `end` marker lines replaced by `block` (markers kept)."""
    i, j = text.find(begin), text.find(end)
    if i < 0 or j < i:
        raise ValueError(f"the markers {begin!r} ... {end!r} are missing or out of order")
    return text[: i + len(begin)] + "\n" + block.strip("\n") + "\n" + text[j:]
