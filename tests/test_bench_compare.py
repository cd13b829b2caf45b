"""bench compare: figures read from two runs' JSON, ratios and which side won; a checkout runs as itself."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from repaint_nerf.core.bench.compare import compare, format_rows, lookup
from repaint_nerf.core.bench.recon import fog_figures

ROOT = Path(__file__).resolve().parents[1]


def test_lookup_dotted_paths_and_sizes():
    data = {"final": {"psnr": 30.5}, "sizes": [{"size": 128, "seconds_to_30": 60.0}, {"size": 256, "x": True}],
            "fog": {"ratio": None}}
    assert lookup(data, "final.psnr") == 30.5
    assert lookup(data, "sizes[128].seconds_to_30") == 60.0
    assert lookup(data, "sizes[512].seconds_to_30") is None
    assert lookup(data, "sizes[256].x") is None  # a flag is no figure
    assert lookup(data, "fog.ratio") is None
    assert lookup(data, "missing.path") is None


def test_compare_ratios_and_direction():
    base = {"final": {"psnr": 25.0}, "render_ms_128": 200.0, "steps_per_s": 2.0}
    head = {"final": {"psnr": 26.0}, "render_ms_128": 100.0, "steps_per_s": 1.0}
    rows = {r["label"]: r for r in compare("recon", base, head)}
    assert rows["render 128x128"]["ratio"] == pytest.approx(0.5) and rows["render 128x128"]["better"] is True
    assert rows["steps per second"]["ratio"] == pytest.approx(0.5) and rows["steps per second"]["better"] is False
    assert rows["final test PSNR"]["better"] is True
    assert rows["peak RSS"]["ratio"] is None and rows["peak RSS"]["better"] is None
    text = format_rows("recon", list(rows.values()))
    assert "render 128x128 ms" in text and "0.500" in text and "worse" in text


def test_compare_a_side_that_did_not_run():
    rows = compare("viewport", None, {"ui_frame_ms_p99": 12.0})
    row = next(r for r in rows if r["label"] == "UI frame p99")
    assert row["base"] is None and row["head"] == 12.0 and row["ratio"] is None


def test_scale_rows_per_size_and_size_ratios():
    base = {"sizes": [{"size": 128, "seconds_to_30": 60.0}, {"size": 256, "seconds_to_30": 300.0}]}
    head = {"sizes": [{"size": 128, "seconds_to_30": 50.0}, {"size": 256, "seconds_to_30": 90.0}]}
    rows = {r["label"]: r for r in compare("scale", base, head)}
    assert rows["256 px: seconds to 30 dB"]["ratio"] == pytest.approx(0.3)
    size_row = rows["time to 30 dB, 256 px / 128 px"]
    assert size_row["base"] == pytest.approx(5.0) and size_row["head"] == pytest.approx(1.8)
    assert size_row["better"] is True


def test_scale_ratios_read_at_the_runs_own_goal():
    """A run told other targets (a real capture that never reaches 30 dB) is compared at its highest one."""
    base = {"targets": [22.0, 24.0], "sizes": [{"size": 128, "seconds_to_24": 40.0, "seconds_to_30": None},
                                                {"size": 512, "seconds_to_24": 200.0}]}
    head = {"targets": [22.0, 24.0], "sizes": [{"size": 128, "seconds_to_24": 30.0}, {"size": 512, "seconds_to_24": 90.0}]}
    rows = {r["label"]: r for r in compare("scale", base, head)}
    assert rows["512 px: seconds to 24 dB"]["ratio"] == pytest.approx(0.45)
    ratio = rows["time to 24 dB, 512 px / 128 px"]
    assert ratio["base"] == pytest.approx(5.0) and ratio["head"] == pytest.approx(3.0)
    assert not any("30 dB" in label for label in rows)


def test_fog_figures():
    steps = [0.4] * 50 + [0.1] * 200
    fog = fog_figures(steps)
    assert fog["ratio"] == pytest.approx(4.0) and fog["first_mean_ms"] == pytest.approx(400.0)
    assert fog_figures([0.1] * 30)["ratio"] is None  # too short a run to say


def test_checkout_runs_its_own_code(tmp_path):
    """The working tree runs through its repaint_nerf link folder, with this interpreter."""
    from repaint_nerf.app.bench.compare import command_for

    cmd, env = command_for(ROOT, tmp_path)
    out = subprocess.run(cmd + ["--version"], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and "repaint-nerf" in out.stdout
    probe = subprocess.run([sys.executable, "-c", "import repaint_nerf.core as c; print(c.__file__)"], env=env,
                           capture_output=True, text=True, timeout=120)
    assert Path(probe.stdout.strip()).resolve() == (ROOT / "core" / "__init__.py").resolve()


def test_a_checkout_does_not_inherit_our_allocator_setting(tmp_path, monkeypatch):
    """core sets PyTorch's huge-page switch for its own process; the base side of a comparison runs with its own
    settings, unless the user set the switch."""
    import repaint_nerf.core as core
    from repaint_nerf.app.bench.compare import command_for

    monkeypatch.setenv(core.THP_ENV, "1")
    monkeypatch.setattr(core, "THP_FROM_USER", False)
    assert core.THP_ENV not in command_for(ROOT, tmp_path)[1]
    monkeypatch.setattr(core, "THP_FROM_USER", True)
    assert command_for(ROOT, tmp_path)[1][core.THP_ENV] == "1"


def test_unknown_ref_is_a_clear_error(tmp_path):
    from repaint_nerf.app.cli import main

    rc = main(["bench", "compare", "--base", "no-such-ref-xyz", "--benches", "recon", "--out", str(tmp_path)])
    assert rc == 2
