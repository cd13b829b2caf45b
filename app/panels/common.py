"""Small widgets the panels share: a disabled-with-reason notice for features not built yet."""
from __future__ import annotations

from imgui_bundle import imgui


def unavailable(app, feature: str) -> bool:
    """Show why `feature` is not available and return True when it is not (the caller then skips its widgets)."""
    reason = app.state.capabilities.get(feature)
    if reason is None:
        return False
    imgui.text_colored(imgui.ImVec4(1.0, 0.7, 0.3, 1.0), f"{feature}: not available yet")
    if imgui.is_item_hovered():
        imgui.set_tooltip(reason)
    return True


def remember_item(app, name: str) -> None:
    """Record the last widget's screen rectangle under `name` (scripted input in tests and benchmarks clicks it)."""
    if app.cache.get("reveal") == name:  # scripted input asked to scroll it into view, as a user would
        imgui.set_scroll_here_y(0.5)
        app.cache.pop("reveal")
    a, b = imgui.get_item_rect_min(), imgui.get_item_rect_max()
    app.cache.setdefault("items", {})[name] = (a.x, a.y, b.x, b.y)
