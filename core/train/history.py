"""Loss/PSNR against training step: the editor's live plot, kept in checkpoints so a reopened workspace
shows its past."""
from __future__ import annotations

from dataclasses import dataclass, field

MAX_POINTS = 5000  # beyond this, every other old point is dropped (the plot stays cheap, the file small)


@dataclass
class TrainingHistory:
    """Parallel lists of step, loss and PSNR."""

    steps: list = field(default_factory=list)
    loss: list = field(default_factory=list)
    psnr: list = field(default_factory=list)

    def add(self, info: dict) -> None:
        """Record a step's info dict (one with 'step', 'loss', 'psnr'); others are ignored."""
        if "step" not in info:
            return
        self.steps.append(float(info["step"]))
        self.loss.append(float(info.get("loss", float("nan"))))
        self.psnr.append(float(info.get("psnr", float("nan"))))
        if len(self.steps) > MAX_POINTS:
            half = MAX_POINTS // 2
            for lst in (self.steps, self.loss, self.psnr):
                del lst[:half:2]

    def copy(self) -> "TrainingHistory":
        return TrainingHistory(list(self.steps), list(self.loss), list(self.psnr))

    def to_dict(self) -> dict:
        # JSON has no NaN: a missing value is null
        return {k: [None if v != v else v for v in getattr(self, k)] for k in ("steps", "loss", "psnr")}

    @staticmethod
    def from_dict(d: dict | None) -> "TrainingHistory":
        d = d or {}
        lists = [[float("nan") if v is None else float(v) for v in d.get(k) or []] for k in ("steps", "loss", "psnr")]
        n = min(len(x) for x in lists)
        return TrainingHistory(*(x[:n] for x in lists))
