"""Packaging: the repository's folders install under the one name `repaint_nerf` (no generic top-level `core`,
`app`, ...), every package folder is listed in pyproject.toml, and no module imports the bare folder names."""
from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = ("core", "app", "shaders", "assets")


def _listed_packages() -> set[str]:
    text = (ROOT / "pyproject.toml").read_text()
    block = re.search(r"^packages = \[(.*?)\]", text, re.S | re.M).group(1)
    return set(re.findall(r'"([\w.]+)"', block))


def test_every_package_folder_is_listed_under_repaint_nerf():
    on_disk = {"repaint_nerf." + str(p.parent.relative_to(ROOT)).replace("/", ".")
               for top in FOLDERS for p in (ROOT / top).rglob("__init__.py")}
    assert len(on_disk) > 15
    assert _listed_packages() == on_disk


def test_the_package_is_importable_by_its_name():
    import repaint_nerf.app.cli as cli
    import repaint_nerf.core.engine as engine

    assert Path(engine.__file__).resolve().parent == ROOT / "core"
    assert callable(cli.main)


def test_no_module_imports_a_bare_folder_name():
    bad = []
    for top in (*FOLDERS, "tests"):
        for p in (ROOT / top).rglob("*.py"):
            for node in ast.walk(ast.parse(p.read_text(), str(p))):
                names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                    [node.module] if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module else []
                bad += [f"{p.relative_to(ROOT)}:{node.lineno} {n}" for n in names if n.split(".")[0] in FOLDERS]
    assert not bad, "\n".join(bad)
