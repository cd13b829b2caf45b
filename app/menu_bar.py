"""The editor's menu bar: a Help menu with every key and mouse binding, and the first-run hint beside it."""
from __future__ import annotations

from imgui_bundle import imgui

from repaint_nerf.app.panels.common import remember_item

# (input, what it does), as app.editor's viewport input handles them.
BINDINGS: tuple[tuple[str, str], ...] = (
    ("left drag", "orbit the camera (Navigate tool)"),
    ("left drag", "draw a patch that selects what it covers (Select patch tool)"),
    ("shift + left drag", "add a patch to the selection"),
    ("ctrl + left drag", "subtract a patch from the selection"),
    ("right drag", "pan (Navigate tool); orbit (Select patch tool)"),
    ("middle drag", "pan"),
    ("mouse wheel", "zoom"),
    ("arrow keys", "orbit"),
    ("+ / -", "zoom in / out"),
    ("R", "reset the view to where it started"),
    ("Enter", "confirm a typed field"),
)
HINT_COLOR = (1.0, 0.85, 0.3, 1.0)


def draw(app) -> float:
    """Draw the menu bar; returns its height (the windows below start there)."""
    if not imgui.begin_main_menu_bar():
        return 0.0
    height = imgui.get_window_height()
    if imgui.begin_menu("Help"):
        _help_items(app)
        imgui.end_menu()
    else:
        remember_item(app, "help_menu")
        imgui.set_item_tooltip("keys and mouse bindings; the first-steps hints")
    hint = app.guide.hint()
    if hint is not None:
        imgui.separator()
        imgui.text_colored(imgui.ImVec4(*HINT_COLOR), hint)
        imgui.set_item_tooltip("the next step of a first edit; this line goes away once you have done it "
                               "(Help > Hide the first-steps hints)")
    imgui.end_main_menu_bar()
    return height


def _help_items(app) -> None:
    imgui.text_disabled("Keys and mouse (over the view)")
    if imgui.begin_table("bindings", 2):
        for key, what in BINDINGS:
            imgui.table_next_row()
            imgui.table_next_column()
            imgui.text(key)
            imgui.table_next_column()
            imgui.text(what)
        imgui.end_table()
    imgui.separator()
    guide = app.guide
    if imgui.menu_item("Show the first-steps hints again", "", False)[0]:
        guide.reset()
    remember_item(app, "help_reset")
    imgui.set_item_tooltip("start the hint line over from the first step")
    if imgui.menu_item("Hide the first-steps hints", "", guide.hidden)[0]:
        guide.set_hidden(not guide.hidden)
    imgui.set_item_tooltip("hide (or show) the hint line in the menu bar")
    imgui.text_disabled("Every command and model path: README.md; `repaint-nerf --help`")
