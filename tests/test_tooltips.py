"""Every control of the editor's panels and menu bar carries a tooltip: each call that draws a control is followed
(within three statements, or in its own `if` body) by `set_item_tooltip` / `set_tooltip`."""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SOURCES = sorted((ROOT / "app" / "panels").glob("*.py")) + [ROOT / "app" / "menu_bar.py"]
CONTROLS = {"button", "small_button", "checkbox", "radio_button", "slider_float", "slider_int", "input_text",
            "input_float", "input_int", "begin_combo", "collapsing_header", "tree_node", "menu_item", "selectable"}
TIPS = {"set_item_tooltip", "set_tooltip"}


def _imgui_calls(nodes) -> set[str]:
    return {n.func.attr for node in nodes for n in ast.walk(node)
            if isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute)
            and isinstance(n.func.value, ast.Name) and n.func.value.id == "imgui"}


def _header(stmt: ast.stmt) -> list:
    """The expressions a statement evaluates before any nested body (where its own controls are drawn)."""
    if isinstance(stmt, (ast.If, ast.While)):
        return [stmt.test]
    value = getattr(stmt, "value", None)
    return [value] if isinstance(stmt, (ast.Assign, ast.AugAssign, ast.AnnAssign, ast.Expr, ast.Return)) and value \
        else []


def _untipped(body: list, where: str) -> list[str]:
    bad = []
    for i, stmt in enumerate(body):
        controls = _imgui_calls(_header(stmt)) & CONTROLS
        if controls and not _imgui_calls([stmt, *body[i + 1:i + 4]]) & TIPS:
            bad.append(f"{where}:{stmt.lineno} {sorted(controls)}")
        for field in ("body", "orelse", "finalbody"):
            inner = getattr(stmt, field, None)
            if isinstance(inner, list) and inner and isinstance(inner[0], ast.stmt):
                bad += _untipped(inner, where)
    return bad


def test_every_control_has_a_tooltip():
    bad = []
    for path in SOURCES:
        bad += _untipped(ast.parse(path.read_text()).body, str(path.relative_to(ROOT)))
    assert not bad, "controls without a tooltip:\n" + "\n".join(bad)


def test_the_check_finds_a_control_without_a_tooltip():
    code = "def draw():\n    if imgui.button('A'):\n        pass\n    x = 1\n    y = 2\n    z = 3\n"
    assert _untipped(ast.parse(code).body, "t") == ["t:2 ['button']"]
