"""The first-run guide: a hint line naming the next step of a first edit, until the user has done it once.

Steps are done by doing them (the editor calls `done(step)` where the action happens), in any order; the hint
is the first step not yet done. What was done is remembered per user (`app.user_settings`), so the hints go away
for good; the Help menu can bring them back or hide them.
"""
from __future__ import annotations

from dataclasses import dataclass

from repaint_nerf.app.user_settings import UserSettings


@dataclass(frozen=True)
class Step:
    """One step of the first edit: its key (what `done` is called with) and the hint that asks for it."""

    key: str
    hint: str


STEPS: tuple[Step, ...] = (
    Step("orbit", "left-drag in the view to orbit while the scene trains (the wheel zooms)"),
    Step("select", "turn on 'Select patch' and drag a rectangle over an object to select it"),
    Step("threshold", "move the Threshold slider until the yellow mask covers just the object"),
    Step("repaint", "type a prompt (e.g. 'make it blue') and press Repaint"),
    Step("compare", "when the edit is done, press Undo and Redo to compare the versions"),
    Step("export", "open Export and press Export mesh to save the result"),
)


class Guide:
    """Which steps this user has done, and the hint for the next one."""

    def __init__(self, settings: UserSettings):
        self.settings = settings
        self._done = set(settings.get("first_steps_done", []))

    @property
    def hidden(self) -> bool:
        return bool(self.settings.get("hints_hidden", False))

    def set_hidden(self, hidden: bool) -> None:
        self.settings.set("hints_hidden", bool(hidden))

    def is_done(self, key: str) -> bool:
        return key in self._done

    def done(self, key: str) -> None:
        """Record that the user did `key` (saved the first time only)."""
        if key not in self._done:
            self._done.add(key)
            self.settings.set("first_steps_done", sorted(self._done))

    def reset(self) -> None:
        """Show every hint again, from the first step."""
        self._done.clear()
        self.settings.set("first_steps_done", [])
        self.set_hidden(False)

    def next_step(self) -> Step | None:
        return None if self.hidden else next((s for s in STEPS if s.key not in self._done), None)

    def hint(self) -> str | None:
        """'Step i/n: ...' for the first step not done, or None when all are (or hints are hidden)."""
        step = self.next_step()
        return None if step is None else f"Step {STEPS.index(step) + 1}/{len(STEPS)}: {step.hint}"
