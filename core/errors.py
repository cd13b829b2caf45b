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


class WorkspaceDamaged(WorkspaceError):
    """A workspace file whose content is not what was written (truncated, altered, missing, foreign): `repair`
    can set it aside and rebuild what depends on it. `workspace` is the folder to repair (None when unknown)."""

    def __init__(self, message: str, path: str | Path | None = None, workspace: str | Path | None = None,
                 hint: str | None = None):
        self.workspace = None if workspace is None else Path(workspace)
        if hint is None and self.workspace is not None:
            hint = (f"run: repaint-nerf repair {self.workspace} (it sets damaged files aside and keeps every "
                    "good version)")
        super().__init__(message, path, hint)


class SaveFailed(WorkspaceError, OSError):
    """A save the file system refused (a full disk, a read-only folder): the previous file is unchanged. Also an
    OSError with the original `errno`, so callers that handled the raw error still do."""

    def __init__(self, path: str | Path, exc: OSError):
        import errno as codes

        why = {codes.ENOSPC: ("the disk is full", "free some space, or save to a folder on another disk"),
               codes.EDQUOT: ("the disk quota is used up", "free some space, or save to a folder on another disk"),
               codes.EROFS: ("the folder is on a read-only file system", "save to a folder you can write to"),
               codes.EACCES: ("the folder is not writable", "make it writable, or save to another folder"),
               codes.EPERM: ("the folder is not writable", "make it writable, or save to another folder")}
        what, hint = why.get(exc.errno, (exc.strerror or str(exc), "check the folder and the disk, then save again"))
        super().__init__(f"cannot save this file: {what} ({exc.strerror or exc})", path,
                         hint=f"{hint}; the previous version of the file is unchanged")
        self.errno, self.strerror, self.filename = exc.errno, exc.strerror, str(path)

    def __str__(self) -> str:
        return str(self.args[0])  # the message and hint, not OSError's '[Errno N] ...' form
