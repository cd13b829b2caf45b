"""User-facing errors: each carries one clear message naming the file and what to do.

The command line and the editor catch `UserError` and show its message without a traceback;
anything else is a bug and is reported as one.
"""
from __future__ import annotations

from pathlib import Path


class UserError(Exception):
    """An error caused by input the user can fix (a path, a file, a value, a missing model)."""

    def __init__(self, message: str, path: str | Path | None = None, hint: str | None = None):
        self.path = None if path is None else Path(path)
        self.hint = hint
        text = message if path is None else f"{path}: {message}"
        if hint:
            text = f"{text}\n  -> {hint}"
        super().__init__(text)


class SceneError(UserError):
    """A dataset or photo folder that cannot be read as a scene."""


class ModelNotFoundError(UserError):
    """A pretrained model that is needed but not present at the configured local path."""


class WorkspaceError(UserError):
    """A workspace folder or file that is missing, corrupt or of another format version."""


class SceneWarning(UserWarning):
    """Something in a dataset that was worked around (frames skipped, a key ignored): said once, never fatal."""
