"""Colour names -> RGB, so an offline recolour can follow a prompt like "make it blue" or take "R,G,B".

Names are matched as whole words, longest first ("light blue" before "blue"); the values are sRGB in
[0, 1], chosen as clear mid-saturation object colours rather than the extreme CSS primaries.
"""
from __future__ import annotations

import re

from repaint_nerf.core.errors import UserError

COLORS: dict[str, tuple[float, float, float]] = {
    "red": (0.85, 0.12, 0.10),
    "dark red": (0.55, 0.05, 0.05),
    "crimson": (0.86, 0.08, 0.24),
    "orange": (0.95, 0.50, 0.08),
    "yellow": (0.95, 0.85, 0.10),
    "gold": (0.85, 0.65, 0.13),
    "lime": (0.55, 0.85, 0.10),
    "green": (0.15, 0.70, 0.20),
    "dark green": (0.05, 0.40, 0.10),
    "olive": (0.50, 0.50, 0.10),
    "teal": (0.05, 0.55, 0.55),
    "cyan": (0.10, 0.80, 0.85),
    "turquoise": (0.25, 0.85, 0.80),
    "light blue": (0.55, 0.75, 0.95),
    "sky blue": (0.45, 0.70, 0.92),
    "blue": (0.12, 0.30, 0.90),
    "dark blue": (0.05, 0.10, 0.50),
    "navy": (0.05, 0.08, 0.40),
    "indigo": (0.29, 0.05, 0.51),
    "purple": (0.50, 0.15, 0.65),
    "violet": (0.56, 0.30, 0.85),
    "magenta": (0.85, 0.10, 0.75),
    "pink": (0.95, 0.55, 0.70),
    "brown": (0.50, 0.30, 0.12),
    "beige": (0.90, 0.85, 0.70),
    "white": (0.95, 0.95, 0.95),
    "silver": (0.75, 0.75, 0.78),
    "grey": (0.50, 0.50, 0.50),
    "gray": (0.50, 0.50, 0.50),
    "black": (0.05, 0.05, 0.05),
}

_NUM = r"\s*([0-9]*\.?[0-9]+)\s*"
_TRIPLE = re.compile(rf"^{_NUM},{_NUM},{_NUM}$")
_HEX = re.compile(r"#?([0-9a-fA-F]{6})\b")


def parse_rgb(text: str) -> tuple[float, float, float]:
    """'R,G,B' (0-255 integers, or floats in [0, 1] when all are <= 1) or '#rrggbb' -> RGB in [0, 1]."""
    s = str(text).strip()
    m = _TRIPLE.match(s)
    if m:
        vals = [float(v) for v in m.groups()]
        if all(v <= 1.0 for v in vals) and any("." in v for v in m.groups()):
            rgb = vals
        else:
            if any(v > 255 for v in vals):
                raise UserError(f"colour '{text}' has a component above 255",
                                hint="give R,G,B as 0-255 integers or 0-1 floats, e.g. --color 30,80,230")
            rgb = [v / 255.0 for v in vals]
        return (rgb[0], rgb[1], rgb[2])
    m = _HEX.fullmatch(s) if s.startswith("#") or len(s) == 6 else None
    if m:
        h = m.group(1)
        return tuple(int(h[i:i + 2], 16) / 255.0 for i in (0, 2, 4))  # type: ignore[return-value]
    raise UserError(f"colour '{text}' is not R,G,B or #rrggbb",
                    hint="give R,G,B as 0-255 integers or 0-1 floats, e.g. --color 30,80,230")


def color_in_prompt(prompt: str) -> tuple[str, tuple[float, float, float]] | None:
    """The last colour name in `prompt` (whole words, multi-word names first) and its RGB, or None.

    The last one wins because prompts read "turn the red ball blue" / "make it blue".
    """
    text = " " + re.sub(r"[^a-z]+", " ", str(prompt).lower()) + " "
    best: tuple[int, str] | None = None
    for name in sorted(COLORS, key=len, reverse=True):
        for m in re.finditer(rf"(?<= ){re.escape(name)}(?= )", text):
            covered = best is not None and best[0] <= m.start() < best[0] + len(best[1])
            if not covered and (best is None or m.start() > best[0]):
                best = (m.start(), name)
    return None if best is None else (best[1], COLORS[best[1]])


def resolve_color(prompt: str = "", color: str | tuple | None = None) -> tuple[float, float, float]:
    """The recolour target: an explicit `color` (text or tuple) wins, else a colour name in the prompt.

    Raises UserError naming both ways when neither gives a colour.
    """
    if color is not None and color != "":
        if isinstance(color, str):
            if color.strip().lower() in COLORS:
                return COLORS[color.strip().lower()]
            return parse_rgb(color)
        vals = tuple(float(c) for c in color)
        if len(vals) != 3:
            raise UserError(f"colour {color!r} needs three components", hint="give R,G,B")
        return vals if max(vals) <= 1.0 else tuple(v / 255.0 for v in vals)  # type: ignore[return-value]
    found = color_in_prompt(prompt)
    if found is None:
        raise UserError(f"no colour name in the prompt {prompt!r}",
                        hint="name a colour (e.g. 'make it blue') or pass --color R,G,B")
    return found[1]
