"""The worker's render scheduling: what a newer view cancels and what it does not (no model needed)."""
from __future__ import annotations

import time

import numpy as np

from repaint_nerf.app.worker import Frame, Worker


class SlowEngine:
    """Renders take ~100 ms in 5 ms rounds and honour `cancel` between rounds, like the real renderer."""

    def __init__(self) -> None:
        self.log: list[tuple[tuple, float, str]] = []
        self.current: tuple | None = None

    def render(self, cameras, scale=1.0, outputs=("rgb",), cancel=None, stride=1.0):
        for _ in range(20):
            if cancel is not None and cancel():
                self.log.append((cameras, scale, "cancelled"))
                return None
            time.sleep(0.005)
        self.log.append((cameras, scale, "done"))
        return {"rgb": np.zeros((2, 2, 3), np.float32)}


def _frames(worker: Worker, until, timeout: float = 5.0) -> list[Frame]:
    frames: list[Frame] = []
    t0 = time.perf_counter()
    while not until(frames) and time.perf_counter() - t0 < timeout:
        frames += [m for m in worker.poll() if isinstance(m, Frame)]
        time.sleep(0.005)
    return frames


def test_a_drag_shows_frames_while_the_camera_keeps_moving():
    """Requests every 20 ms, faster than a 100 ms render: each first frame of a view finishes and is shown."""
    engine = SlowEngine()
    worker = Worker(engine, rest_s=10.0).start()
    try:
        t0 = time.perf_counter()
        i = 0
        while time.perf_counter() - t0 < 0.5:
            worker.request_render(("view", i), key=(i,))
            i += 1
            time.sleep(0.02)
        frames = _frames(worker, lambda fs: any(f.key == (i - 1,) for f in fs))
    finally:
        worker.stop()
    assert len(frames) >= 3, frames
    assert frames[-1].key == (i - 1,)  # the newest view is served once the drag ends
    assert not any(what == "cancelled" for _, _, what in engine.log) and worker.cancelled == 0
    # views the worker never reached (it was rendering an older one) are counted as dropped, never rendered
    rendered = {c for c, _, _ in engine.log}
    assert worker.dropped == i - len(rendered) > 0


def test_a_move_cancels_the_refinement_of_a_resting_view():
    engine = SlowEngine()
    worker = Worker(engine, rest_s=0.0).start()
    try:
        worker.request_render("a", key=("a",))
        _frames(worker, lambda fs: len(fs) >= 1)  # the first frame, at the controller's scale
        time.sleep(0.03)  # now refining at a finer scale
        worker.request_render("b", key=("b",))
        frames = _frames(worker, lambda fs: any(f.key == ("b",) for f in fs))
    finally:
        worker.stop()
    first_scale = engine.log[0][1]
    assert any(c == "a" and s > first_scale and what == "cancelled" for c, s, what in engine.log), engine.log
    assert worker.cancelled == sum(what == "cancelled" for _, _, what in engine.log) >= 1 and worker.dropped == 0
    assert frames and frames[0].key == ("b",)


def test_the_first_frame_of_a_large_view_renders_a_bounded_number_of_rays():
    """Before any frame is measured, a 439x781 view (a portrait capture in a 1280x800 window) is first rendered with at
    most FIRST_FRAME_RAYS rays, not at the controller's 0.25 (21k rays: 33 s on the 70-step fox capture)."""
    from repaint_nerf.app.resolution import FIRST_FRAME_RAYS
    from repaint_nerf.core.scene.cameras import Cameras

    engine = SlowEngine()
    worker = Worker(engine, rest_s=10.0).start()
    try:
        view = Cameras.create(np.eye(4), 500.0, 500.0, 219.5, 390.5, 439, 781)
        worker.request_render(view, key=("v",))
        _frames(worker, lambda fs: len(fs) >= 1)
    finally:
        worker.stop()
    scale = engine.log[0][1]
    assert 0 < (scale * 439) * (scale * 781) <= FIRST_FRAME_RAYS + 1 and scale < 0.25


class ThreadEngine(SlowEngine):
    """Records the CPU threads torch gives the worker's renders and training steps."""

    def __init__(self) -> None:
        super().__init__()
        self.render_threads: list[tuple[float, int]] = []
        self.train_threads: list[int] = []

    def render(self, cameras, scale=1.0, outputs=("rgb",), cancel=None, stride=1.0):
        import torch

        self.render_threads.append((scale, torch.get_num_threads()))
        return super().render(cameras, scale, outputs, cancel)

    def can_train(self) -> bool:
        return True

    def train_for(self, seconds, stop=None, interlude=None):
        import torch

        self.train_threads.append(torch.get_num_threads())
        time.sleep(0.01)
        return {"step": len(self.train_threads)}


def test_renders_of_a_navigated_view_leave_the_ui_a_core(monkeypatch):
    """Within the navigation hold a view renders on `nav_threads` (the UI draws on the other core); the sharp
    preview after the hold and the training steps run on every thread, and the worker's count is restored."""
    import torch

    count = [2]  # torch's thread count, as a 2-core machine starts it (a 1-core CI machine would hide the change)
    monkeypatch.setattr(torch, "get_num_threads", lambda: count[0])
    monkeypatch.setattr(torch, "set_num_threads", lambda n: count.__setitem__(0, n))
    engine = ThreadEngine()
    worker = Worker(engine, rest_s=0.05, nav_hold_s=0.3, nav_threads=1, preview_interval_s=0.0).start()
    try:
        worker.request_render("a", key=("a",))
        t0 = time.perf_counter()
        while len(engine.render_threads) < 3 and time.perf_counter() - t0 < 5:  # a preview after training resumed
            worker.poll()
            time.sleep(0.01)
    finally:
        worker.stop()
    first, refined, preview = engine.render_threads[:3]
    assert first[1] == 1 and refined == (1.0, 1)  # the move's frame and its refinement, within the hold
    assert preview == (1.0, 2) and engine.train_threads and set(engine.train_threads) == {2}
    assert count[0] == 2


class TimedEngine(ThreadEngine):
    """Renders take `delay` seconds, all at once (no rounds)."""

    def __init__(self, delay: float) -> None:
        super().__init__()
        self.delay = delay

    def render(self, cameras, scale=1.0, outputs=("rgb",), cancel=None, stride=1.0):
        import torch

        self.render_threads.append((scale, torch.get_num_threads()))
        time.sleep(self.delay)
        return {"rgb": np.zeros((2, 2, 3), np.float32)}

    def can_train(self) -> bool:
        return False


def test_costly_rays_navigate_on_every_thread(monkeypatch):
    """A view whose one-thread frames miss the target even at the scale floor (a real capture's contracted room)
    moves on every thread; once every thread renders well under the target, navigation narrows again."""
    import torch

    from repaint_nerf.app.resolution import MIN_SCALE

    count = [2]
    monkeypatch.setattr(torch, "get_num_threads", lambda: count[0])
    monkeypatch.setattr(torch, "set_num_threads", lambda n: count.__setitem__(0, n))
    engine = TimedEngine(delay=0.06)  # 3x a 20 ms target
    worker = Worker(engine, target_ms=20.0, rest_s=10.0, nav_hold_s=5.0, nav_threads=1).start()

    def moves(n: int) -> list:
        for i in range(n):
            before = len(engine.render_threads)
            worker.request_render("a", key=(len(engine.render_threads), i))
            _frames(worker, lambda fs: len(fs) >= 1)
            assert len(engine.render_threads) == before + 1
        return engine.render_threads[-n:]

    try:
        slow = moves(6)
        engine.delay = 0.005  # the field got cheap (it trained): a quarter of the target on every thread
        fast = moves(3)
    finally:
        worker.stop()
    floor = next(i for i, (sc, _) in enumerate(slow) if sc <= MIN_SCALE)
    assert all(n == 1 for _, n in slow[:floor + 1])  # one thread until a frame at the floor misses the target
    assert slow[-1][1] == 2 and worker.nav_threads == 1
    assert fast[0][1] == 2 and fast[-1][1] == 1
    assert count[0] == 2


def test_costly_navigation_ends_when_one_thread_would_hold_the_target(monkeypatch):
    """The controller keeps every frame near the target, so the release judges a frame's cost at the floor's pixels
    on one thread; a frame at target cost far above the floor ends the costly state, one just above it does not,
    and a new scene starts narrow."""
    import torch

    monkeypatch.setattr(torch, "get_num_threads", lambda: 2)
    worker = Worker(ThreadEngine(), target_ms=20.0, nav_threads=1)
    floor, top = worker.controller.min_scale, worker.controller.max_stride
    worker._judge_nav_cost(40.0, floor, 1.0, narrow=True)  # 2x the target, but the step can still lengthen
    assert not worker.nav_costly
    worker._judge_nav_cost(40.0, floor, top, narrow=True)  # 2x the target on one thread at the floor and top stride
    assert worker.nav_costly
    worker._judge_nav_cost(20.0, 1.1 * floor, top, narrow=False)  # on one thread at the floor: ~33 ms
    assert worker.nav_costly
    worker._judge_nav_cost(20.0, 3.0 * floor, top, narrow=False)  # ~4.4 ms
    assert not worker.nav_costly
    worker._judge_nav_cost(40.0, floor, top, narrow=True)
    assert worker.nav_costly
    worker._judge_nav_cost(20.0, floor, 1.0, narrow=False)  # at the top stride on one thread: ~10 ms
    assert not worker.nav_costly
    worker._judge_nav_cost(40.0, floor, top, narrow=True)
    worker.forget_costs()
    assert not worker.nav_costly


def test_feature_frames_keep_every_thread(monkeypatch):
    """The selection tool's views carry features, which a patch waits for: they render on every thread."""
    import torch

    count = [2]
    monkeypatch.setattr(torch, "get_num_threads", lambda: count[0])
    monkeypatch.setattr(torch, "set_num_threads", lambda n: count.__setitem__(0, n))
    engine = ThreadEngine()
    worker = Worker(engine, rest_s=10.0, nav_hold_s=5.0, nav_threads=1).start()
    try:
        worker.request_render("a", key=("a",), outputs=("rgb", "feature"))
        _frames(worker, lambda fs: len(fs) >= 1)
    finally:
        worker.stop()
    assert engine.render_threads[0][1] == 2


def test_a_resting_view_refines_by_doubling_and_skips_a_step_near_its_final_scale():
    """Refinement doubles the scale, but renders the final picture at once when the doubled scale would be within
    worker.REFINE_SKIP of the final one (the engine's cap, or 1): a step at 0.8 costs 64% of the final render."""
    from types import SimpleNamespace

    from repaint_nerf.app.worker import RenderRequest

    engine = SimpleNamespace(max_scale=lambda cameras: cameras)  # the request's 'cameras' is its cap here
    worker = Worker(engine, rest_s=0.0)

    def next_after(served: float, cap: float) -> float | None:
        req = RenderRequest(cap, key=(cap,), serial=1, time=0.0)
        worker._served = (1, served)
        return worker._next_scale(req)

    assert next_after(0.1, 1.0) == 0.2
    assert next_after(0.3, 1.0) == 0.6
    assert next_after(0.4, 1.0) == 1.0  # not 0.8
    assert next_after(0.07, 0.33) == 0.14
    assert next_after(0.14, 0.33) == 1.0  # the engine caps it at 0.33, not a step at 0.28 first
    assert next_after(1.0, 1.0) is None


class StrideEngine(TimedEngine):
    """Records the marching stride of each render."""

    def __init__(self, delay: float) -> None:
        super().__init__(delay)
        self.strides: list[tuple[float, float, tuple]] = []

    def render(self, cameras, scale=1.0, outputs=("rgb",), cancel=None, stride=1.0):
        self.strides.append((scale, stride, tuple(outputs)))
        return super().render(cameras, scale, outputs, cancel, stride)


def test_a_moving_view_at_the_floor_marches_the_controllers_stride_and_its_refinement_the_full_step():
    """The controller lengthens the step only at the scale floor; the first frame of a navigated view renders with
    it, and so does a feature view's first frame (the selection tool's, shown while its sharp frame renders), while
    the resting views' refinements march the normal step."""
    engine = StrideEngine(delay=0.02)  # at the 20 ms target: the controller keeps its scale and stride
    worker = Worker(engine, target_ms=20.0, rest_s=0.05, nav_hold_s=5.0, nav_threads=None)
    worker.controller.scale, worker.controller.stride = worker.controller.min_scale, 3.0
    worker.controller.measured = True
    worker.start()
    try:
        worker.request_render("a", key=("a",))
        _frames(worker, lambda fs: any(f.final for f in fs))
        worker.request_render("b", key=("b",), outputs=("rgb", "feature"))
        _frames(worker, lambda fs: any(f.final and f.key == ("b",) for f in fs))
    finally:
        worker.stop()
    first, *refined = [e for e in engine.strides if "feature" not in e[2]]
    assert first[:2] == (worker.controller.min_scale, 3.0)
    assert refined and all(stride == 1.0 for _, stride, _ in refined) and refined[-1][0] == 1.0
    first_feature, *refined_feature = [e for e in engine.strides if "feature" in e[2]]
    assert first_feature[:2] == (worker.controller.min_scale, 3.0)
    assert refined_feature and all(stride == 1.0 for _, stride, _ in refined_feature)


class SteppingEngine(SlowEngine):
    """Training steps of a 150-ms forward and a 150-ms backward pass, with the trainer's interlude between them."""

    def __init__(self) -> None:
        super().__init__()
        self.events: list[str] = []

    def render(self, cameras, scale=1.0, outputs=("rgb",), cancel=None, stride=1.0):
        self.events.append(f"render {cameras}")
        return {"rgb": np.zeros((2, 2, 3), np.float32)}

    def can_train(self) -> bool:
        return True

    def note(self, what: str) -> str:
        self.events.append(what)
        return what

    def train_for(self, seconds, stop=None, interlude=None):
        self.events.append("forward")
        time.sleep(0.15)
        if interlude is not None:
            interlude()
        self.events.append("backward")
        time.sleep(0.15)
        self.events.append("end")
        return {"step": self.events.count("end")}


def test_a_new_view_renders_within_a_training_step_and_a_command_after_it():
    """A view requested during a step's forward pass is rendered before its backward pass (the trainer's
    interlude), not after the step; a command waits for the step's end (it may replace what the step trains)."""
    engine = SteppingEngine()
    worker = Worker(engine, rest_s=10.0).start()
    try:
        t0 = time.perf_counter()
        while engine.events[-1:] != ["forward"] and time.perf_counter() - t0 < 5:
            time.sleep(0.002)
        worker.request_render("a", key=("a",))
        worker.call(engine.note, "command")
        frames = _frames(worker, lambda fs: len(fs) >= 1)
        t0 = time.perf_counter()
        while "command" not in engine.events and time.perf_counter() - t0 < 5:
            time.sleep(0.005)
    finally:
        worker.stop()
    assert frames and frames[0].key == ("a",)
    i = engine.events.index("render a")
    assert engine.events[i - 1] == "forward" and engine.events[i + 1] == "backward", engine.events
    assert engine.events[engine.events.index("command") - 1] == "end", engine.events
