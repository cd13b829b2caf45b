"""What every export shares: output-path checks with clear messages, atomic writes, and progress / cancel
callbacks (the editor's worker passes its own; the command line passes a tqdm bar)."""
from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Callable, Iterator

from repaint_nerf.core.errors import UserError
from repaint_nerf.core.workspace.atomic import atomic_path

# progress(fraction in [0, 1], what is being done); cancel() -> True stops the export between work items.
Progress = Callable[[float, str], None]
Cancel = Callable[[], bool]
EXPORT_FILE_MODE, EXPORT_DIR_MODE = 0o644, 0o755  # like files a user saves (temp files start private)


class ExportCancelled(UserError):
    """The user cancelled an export; nothing was written under the final name."""


def check_output_file(path: str | Path, suffixes: tuple[str, ...], what: str) -> Path:
    """The output file as a Path, with a suffix from `suffixes` and a folder that exists (it is made) and can be
    written to; otherwise a UserError naming the path."""
    path = Path(path).expanduser().absolute()  # messages name the file wherever the program was started
    if path.suffix.lower() not in suffixes:
        raise UserError(f"cannot tell which {what} format to write from the name", path,
                        hint=f"end the file name in one of: {', '.join(suffixes)}")
    if path.is_dir():
        raise UserError(f"this is a folder, not a {what} file name", path,
                        hint=f"add a file name ending in {suffixes[0]}")
    check_output_dir(path.parent, what)
    return path


def check_output_dir(folder: str | Path, what: str) -> Path:
    """Make `folder` (and its parents) and check it can be written to, else a UserError naming it."""
    folder = Path(folder).expanduser()
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"cannot make the folder for the {what} ({exc.strerror or exc})", folder,
                        hint="choose a folder you can write to") from None
    if not folder.is_dir() or not os.access(folder, os.W_OK | os.X_OK):
        raise UserError(f"cannot write the {what} into this folder", folder, hint="choose a folder you can write to")
    return folder


@contextlib.contextmanager
def atomic_output(path: Path, what: str) -> Iterator[Path]:
    """A temporary path beside `path` that becomes `path` only when the block ends without error (a killed or
    cancelled export leaves no file under the final name); OS errors become a UserError naming `path`."""
    try:
        with atomic_path(path) as tmp:
            yield tmp
            os.chmod(tmp, EXPORT_FILE_MODE)  # the temp file is private (mkstemp); an export is for sharing
    except OSError as exc:
        raise UserError(f"cannot write the {what} ({exc.strerror or exc})", path,
                        hint="choose a folder you can write to, with free space") from None


def checkpoint(cancel: Cancel | None, progress: Progress | None, fraction: float, text: str) -> None:
    """Report progress and raise ExportCancelled when the user asked to stop."""
    if cancel is not None and cancel():
        raise ExportCancelled("export cancelled; no file was written", hint="start it again when you want the file")
    if progress is not None:
        progress(min(max(float(fraction), 0.0), 1.0), text)
