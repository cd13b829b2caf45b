"""Layering: `core` is the engine and imports nothing above it (the editor, the CLI, the window or GUI
toolkits), at module level or inside a function; the renderer's grid and marcher do not import each other."""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FORBIDDEN = ("repaint_nerf.app", "app", "glfw", "imgui_bundle")  # app: the folder's old import name


def _imports(path: Path) -> list[tuple[int, str]]:
    """(line, imported module) of every import statement in a file, however deeply nested."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out.append((node.lineno, node.module))
    return out


def test_core_imports_nothing_above_it():
    files = sorted((ROOT / "core").rglob("*.py"))
    assert len(files) > 50  # the walk found the package
    bad = [f"{p.relative_to(ROOT)}:{line} imports {mod}" for p in files for line, mod in _imports(p)
           if any(mod == f or mod.startswith(f + ".") for f in FORBIDDEN)]
    assert not bad, "\n".join(bad)


def test_the_walk_would_catch_a_nested_import(tmp_path):
    p = tmp_path / "m.py"
    p.write_text("def f():\n    from repaint_nerf.app.worker import Worker\n    import glfw\n")
    assert [m for _, m in _imports(p)] == ["repaint_nerf.app.worker", "glfw"]


def test_occupancy_and_raymarch_do_not_import_each_other():
    occ = {m for _, m in _imports(ROOT / "core/render/occupancy.py")}
    march = {m for _, m in _imports(ROOT / "core/render/raymarch.py")}
    assert not ("repaint_nerf.core.render.raymarch" in occ and "repaint_nerf.core.render.occupancy" in march)
    assert "repaint_nerf.core.render.raymarch" not in occ
