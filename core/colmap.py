"""pycolmap, imported in one place: importing it installs glog's failure-signal handler, which turns a plain
SIGTERM (closing the editor, stopping a command) into a native stack trace on stderr. The handler a process
had for SIGTERM before the import is put back, so a stop stays quiet. Import pycolmap from here."""
from __future__ import annotations

import signal
import threading

_before = signal.getsignal(signal.SIGTERM) if threading.current_thread() is threading.main_thread() else None

import pycolmap  # noqa: E402  (the point of this module: the handler is read before and restored after)

if _before is not None:  # signal handlers can only be set from the main thread
    signal.signal(signal.SIGTERM, _before)

__all__ = ["pycolmap"]
