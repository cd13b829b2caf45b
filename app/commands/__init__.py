"""Subcommands of `repaint-nerf`, one module each (discovered by app/cli.py)."""
