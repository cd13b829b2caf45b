"""The viewport's dynamic-resolution controller follows instant-ngp's rule (sqrt ratio, clamp, 20% band)."""
import math

from repaint_nerf.app.resolution import DynamicResolution


def test_scales_by_sqrt_of_time_ratio():
    c = DynamicResolution(target_ms=50.0, scale=0.5)
    assert math.isclose(c.update(200.0), 0.5 * math.sqrt(50 / 200))  # 4x too slow -> half the scale
    c = DynamicResolution(target_ms=50.0, scale=0.25)
    assert math.isclose(c.update(12.5), 0.25 * 2.0)  # 4x too fast -> double


def test_no_change_inside_the_band_and_change_just_outside():
    c = DynamicResolution(target_ms=50.0, scale=0.5)
    for ms in (40.0, 45.0, 50.0, 55.0, 60.0):
        assert c.update(ms) == 0.5
    assert c.update(61.0) < 0.5
    c = DynamicResolution(target_ms=50.0, scale=0.5)
    assert c.update(39.0) > 0.5


def test_clamped_to_sixteenth_and_one():
    c = DynamicResolution(target_ms=10.0, scale=0.1)
    for _ in range(10):
        c.update(1e6)
    assert c.scale == 1.0 / 16.0
    for _ in range(10):
        c.update(1e-3)
    assert c.scale == 1.0


def test_uses_the_scale_the_frame_was_rendered_at_and_ignores_bad_times():
    c = DynamicResolution(target_ms=50.0, scale=0.5)
    assert math.isclose(c.update(200.0, at_scale=1.0), 0.5)
    assert c.update(float("nan")) == 0.5 and c.update(0.0) == 0.5


def test_converges_on_a_quadratic_cost_model():
    c = DynamicResolution(target_ms=40.0, scale=1.0)
    for _ in range(6):
        c.update(160.0 * c.scale ** 2)  # render cost ~ pixels ~ scale^2; full res costs 160 ms
    assert abs(160.0 * c.scale ** 2 - 40.0) <= 0.2 * 40.0


def test_the_first_view_renders_a_bounded_number_of_rays_then_the_measured_time_rules():
    """A scene opens with at most FIRST_FRAME_RAYS rays (a foggy real capture costs ~1 ms a ray on a CPU); a view
    smaller than that keeps the controller's scale; once a frame is measured the size no longer caps it."""
    from repaint_nerf.app.resolution import FIRST_FRAME_RAYS

    c = DynamicResolution(target_ms=40.0, scale=0.25)
    s = c.for_view(439 * 781)  # the fox capture's photo frame in a 1280x800 window
    assert math.isclose(s, math.sqrt(FIRST_FRAME_RAYS / (439 * 781))) and (s * 439) * (s * 781) <= FIRST_FRAME_RAYS + 1
    assert DynamicResolution(scale=0.25).for_view(100 * 100) == 0.25 and DynamicResolution().for_view(None) == 0.25
    assert DynamicResolution(scale=0.25).for_view(10 ** 9) == 1.0 / 16.0  # never below the floor
    c.update(1.0, at_scale=s)  # far faster than the target: the next views render finer than the cap
    assert c.for_view(439 * 781) > s


def test_below_the_floor_the_step_lengthens_and_on_the_way_back_shortens_first():
    """A frame's cost goes with scale^2 / stride: a view too costly at the 1/16 floor converges on a longer step
    (within MAX_STRIDE) at the floor, and when it gets cheap the stride returns to 1 before the scale rises."""
    from repaint_nerf.app.resolution import MAX_STRIDE, MIN_SCALE

    c = DynamicResolution(target_ms=20.0, scale=0.25)
    full = 20.0 * 2.5 / MIN_SCALE ** 2  # at the floor and the normal step: 2.5x the target

    def frame(cost: float) -> None:
        c.update(cost * c.scale ** 2 / c.stride)
        assert c.stride == 1.0 or c.scale == MIN_SCALE  # a longer step only at the floor
        assert 1.0 <= c.stride <= MAX_STRIDE

    for _ in range(8):
        frame(full)
    assert c.scale == MIN_SCALE and abs(full * MIN_SCALE ** 2 / c.stride - 20.0) <= 0.2 * 20.0
    frame(full / 100.0)  # trained: 40x cheaper than the target needs at the floor
    assert c.stride == 1.0 and c.scale > MIN_SCALE
    for _ in range(8):
        frame(full * 100.0)  # never held: the stride stops at its cap
    assert c.scale == MIN_SCALE and c.stride == MAX_STRIDE
