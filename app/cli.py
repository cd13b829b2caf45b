"""The `repaint-nerf` command line.

Each subcommand is a module in `app/commands/` with `NAME`, `HELP`, `add_arguments(parser)` and
`run(args) -> int`; modules import `core` lazily inside `run` so `--help` stays fast. With no
subcommand the editor opens on the demo scene.
"""
from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

VERSION = "0.1.0"


def _command_modules():
    import repaint_nerf.app.commands as pkg

    for info in sorted(pkgutil.iter_modules(pkg.__path__), key=lambda m: m.name):
        if not info.name.startswith("_"):
            yield importlib.import_module(f"repaint_nerf.app.commands.{info.name}")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="repaint-nerf",
        description="Reconstruct a scene, select an object through a feature field, repaint it under "
                    "diffusion guidance. With no command, the editor opens on the built-in demo scene.")
    parser.add_argument("--version", action="version", version=f"repaint-nerf {VERSION}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for mod in _command_modules():
        p = sub.add_parser(mod.NAME, help=mod.HELP, description=mod.HELP)
        mod.add_arguments(p)
        p.set_defaults(_run=mod.run)
    return parser


def show_scene_warnings() -> None:
    """Print dataset warnings (core.errors.SceneWarning) as one plain `warning:` line, not Python's file:line form."""
    import warnings

    from repaint_nerf.core.errors import SceneWarning

    previous = warnings.showwarning
    if getattr(previous, "scene_warnings", False):
        return

    def show(message, category, filename, lineno, file=None, line=None):
        if issubclass(category, SceneWarning):
            print(f"warning: {message}", file=sys.stderr)
        else:
            previous(message, category, filename, lineno, file, line)

    show.scene_warnings = True
    warnings.showwarning = show


def main(argv: list[str] | None = None) -> int:
    from repaint_nerf.core.errors import UserError

    argv = sys.argv[1:] if argv is None else argv
    show_scene_warnings()
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "_run", None) is None:
        args = parser.parse_args(["open", *argv])
    args._argv = list(argv)  # the command line as typed (a bench records it in its JSON)
    try:
        return int(args._run(args) or 0)
    except UserError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
