"""The version index rebuilt from what survives: the good version files' own stamps, and the old index where it
is still readable. Pure data in, data out; `core.workspace.repair` does the file work around it."""
from __future__ import annotations

from typing import Any


def _place_orphan(history: list[str], vid: str, parent: str | None) -> list[str]:
    """The history after `vid` is saved behind `parent` (what `Workspace.save_version` would have written had
    its index write not been cut off): the redo line after the parent is dropped."""
    if parent in history:
        return history[: history.index(parent) + 1] + [vid]
    return history + [vid]


def _chain(good: dict[str, dict]) -> list[str]:
    """An undo/redo line with no index to go by: from the newest good version back through its parents (a
    parent that is gone is bridged to the next older good version)."""
    ids = sorted(good)
    line: list[str] = []
    vid: str | None = ids[-1] if ids else None
    while vid is not None:
        line.append(vid)
        parent = good[vid].get("parent")
        older = [v for v in ids if v < vid and v not in line]
        vid = parent if parent in good and parent not in line else (older[-1] if older else None)
    return line[::-1]


def rebuild_index(good: dict[str, dict[str, Any]], old: dict | None) -> dict:
    """The index over the `good` versions (id -> VersionInfo dict). With the `old` index readable, its undo/redo
    line and position are kept, versions that are gone leave it, and a version saved but never indexed (a save
    killed between its file and the index) joins it as its save would have; without one the line follows the
    newest version's parents. The current version is the old one when it is good, else the nearest good one
    before it on the line, else the newest."""
    if old is None:
        history = _chain(good)
        return {"versions": dict(sorted(good.items())), "history": history, "current": len(history) - 1}
    old_history = list(old["history"])
    cur_old = old_history[old["current"]] if 0 <= old["current"] < len(old_history) else None
    history = [v for v in old_history if v in good]
    current = cur_old if cur_old in good else None
    if current is None and cur_old is not None:
        before = [v for v in old_history[: old_history.index(cur_old)] if v in good]
        current = before[-1] if before else None
    for vid in sorted(set(good) - set(old["versions"])):
        history = _place_orphan(history, vid, good[vid].get("parent"))
        current = vid
    if current is None and history:
        current = history[-1]
    return {"versions": dict(sorted(good.items())), "history": history,
            "current": history.index(current) if current in history else -1}
