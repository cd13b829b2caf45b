"""Per-user editor settings (which first-run hints were followed), in one small JSON file.

The file lives in `$REPAINT_NERF_CONFIG_DIR` when set (tests point it at a temporary folder), else in
`$XDG_CONFIG_HOME/repaint-nerf` or `~/.config/repaint-nerf`. A missing or unreadable file is an empty one:
settings are a convenience, never a reason not to open the editor.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

ENV = "REPAINT_NERF_CONFIG_DIR"


def config_dir() -> Path:
    """The folder of this user's settings (created on the first save, not here)."""
    if os.environ.get(ENV):
        return Path(os.environ[ENV])
    base = os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(base) / "repaint-nerf"


class UserSettings:
    """A dict read from and written back to `settings.json` in the user's config folder."""

    def __init__(self, path: Path | None = None):
        self.path = path or config_dir() / "settings.json"
        try:
            data = json.loads(self.path.read_text())
        except (OSError, ValueError):
            data = {}
        self.data: dict[str, Any] = data if isinstance(data, dict) else {}

    def get(self, key: str, default: Any = None) -> Any:
        return self.data.get(key, default)

    def set(self, key: str, value: Any) -> None:
        """Store `value` and write the file at once (atomically); a failed write is kept in memory only."""
        from repaint_nerf.core.workspace import atomic

        self.data[key] = value
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            atomic.write_json(self.path, self.data)
        except OSError:
            pass
