"""A virtual X display (Xvfb) for real windows on a machine without one: GUI tests and `bench viewport`."""
from __future__ import annotations

import os
import shutil
import subprocess
import time
from pathlib import Path


def start_xvfb(first: int = 99, last: int = 200, screen: str = "1600x1000x24") -> tuple[subprocess.Popen, str]:
    """Start Xvfb on the first free display number in [first, last), wait for its socket, set $DISPLAY.

    Returns (process, display); raises FileNotFoundError when Xvfb is not installed.
    """
    exe = shutil.which("Xvfb")
    if exe is None:
        raise FileNotFoundError("Xvfb is not installed: run `bash install.sh` (it installs the xvfb package)")
    num = next(n for n in range(first, last) if not Path(f"/tmp/.X{n}-lock").exists())
    proc = subprocess.Popen([exe, f":{num}", "-screen", "0", screen, "-nolisten", "tcp"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    for _ in range(100):
        if Path(f"/tmp/.X11-unix/X{num}").exists():
            break
        time.sleep(0.05)
    os.environ["DISPLAY"] = f":{num}"
    return proc, f":{num}"
