"""`repaint-nerf docs`: the README's figure table and docs/BENCHMARKS.md generated from hand-made bench JSON of
each bench's schema; a missing or broken file names the command that measures it; the repository's own pages are
up to date with docs/bench/."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from repaint_nerf.app.cli import main

ROOT = Path(__file__).resolve().parents[1]
README = "# x\n\nintro\n\n<!-- figures:begin -->\nold table\n<!-- figures:end -->\n\nrest\n"
NERFACTO = {"seconds_to_25_4": 560.0, "render_s_128": 7.7}
RECON = {"scene": {"name": "demo", "train_views": 100, "size": [128, 128]}, "device": "cpu:x86_64 x2 threads",
         "curve": [{"seconds": 0.0, "step": 0, "psnr": 9.1}, {"seconds": 41.7, "step": 700, "psnr": 25.6}],
         "final": {"psnr": 33.97, "ssim": 0.986, "steps": 3000, "seconds": 180.0}, "steps_per_s": 16.7,
         "seconds_to_25_4": 41.7, "render_ms_128": 54.0, "peak_rss_mb": 1500.0,
         "samples_per_ray": {"with_grid": 4.4, "without_grid": 108.0},
         "breakdown": {"step_ms": 60.0, "ms": {"encoding": 30.0, "backward": 30.0},
                       "fraction": {"encoding": 0.5, "backward": 0.5}},
         "reference": {"nerfacto": NERFACTO}, "measured": "2026-11-30",
         "command": "repaint-nerf bench recon --seconds 180 --json docs/bench/recon.json"}
VIEWPORT = {"move_to_first_frame_ms_p50": 61.0, "ui_frame_ms_p99": 30.2, "patch_to_mask_ms": 66.0,
            "device": "cpu:x86_64 x2 threads", "measured": "2026-12-01"}


def _final(iou: float, best: float) -> dict:
    return {"iou": iou, "auto_threshold": 0.55, "iou_fixed": 0.8, "best_iou": best, "best_threshold": 0.6,
            "train_iou": 0.92, "no_geometry": {"iou": 0.7}, "editor": {"iou": 0.9}}


MASK = {"benchmark": "mask", "teacher": "default", "steps": 2000, "device": "cpu", "measured": "2026-12-02",
        "final": {"iou": 0.933, "mean_iou": 0.968, "min_iou_fixed": 0.75},
        "presets": {"demo": {"final": _final(0.990, 0.992), "patch_to_mask_ms": 60.0},
                    "toys": {"final": _final(0.933, 0.935), "patch_to_mask_ms": 80.0}}}
SDCOST = {"architecture": "Stable Diffusion 1.5 (random weights from its configuration)", "device": "cpu",
          "render_size": 128, "threads": 2, "measured": "2026-12-03",
          "options": {"baseline": {"settings": {"sds_resolution": 512}, "step_seconds": 26.9, "peak_rss_mb": 8200.0},
                      "bf16+tiny_ae+nhwc+tome": {"settings": {"sds_resolution": 512}, "step_seconds": 4.74},
                      "bf16+tiny_ae+sds_256": {"settings": {"sds_resolution": 256}, "step_seconds": 1.28}},
          "speedup_vs_baseline": {"baseline": 1.0}}


def _docs(tmp_path: Path, files: dict[str, object], *extra: str) -> tuple[int, str, str]:
    bench = tmp_path / "bench"
    bench.mkdir(exist_ok=True)
    for name, data in files.items():
        (bench / name).write_text(data if isinstance(data, str) else json.dumps(data))
    readme = tmp_path / "README.md"
    if not readme.is_file():
        readme.write_text(README)
    out = tmp_path / "docs" / "BENCHMARKS.md"
    rc = main(["docs", "--bench-dir", str(bench), "--readme", str(readme), "--out", str(out), *extra])
    return rc, readme.read_text(), out.read_text() if out.is_file() else ""


def test_every_headline_figure_comes_from_its_json(tmp_path):
    rc, readme, page = _docs(tmp_path, {"recon.json": RECON, "viewport.json": VIEWPORT, "mask.json": MASK,
                                        "sdcost.json": SDCOST})
    assert rc == 0
    table = readme.split("<!-- figures:begin -->")[1].split("<!-- figures:end -->")[0]
    assert "old table" not in table and readme.endswith("rest\n") and readme.startswith("# x\n\nintro")
    for text in ("42 s; 34.0 dB after 180 s", "nerfacto: 560 s", "54 ms", "nerfacto: 7.7 s", "61 / 30.2 / 66 ms",
                 "mean 0.968, worst 0.933 (2 presets)", "worst 0.750", "mean 0.964", "4.74 s at 512 px",
                 "1.28 s at 256 px", "26.9 s: fp32 UNet and VAE", "2026-11-30", "2026-12-03",
                 "`repaint-nerf bench recon --seconds 180`"):
        assert text in table, text
    assert "not measured" not in table and "--json" not in table
    assert len([line for line in table.splitlines() if line.startswith("| ")]) == 7  # header, rule, five figures
    for text in ("## Reconstruction speed", "| 41.7 | 700 | 25.60 |", "| toys | 0.933 at 0.55 |",
                 "| bf16+tiny_ae+sds_256 | 1.28 |", "| patch_to_mask_ms | 66.0 |", "Measured 2026-12-02"):
        assert text in page, text


def test_missing_and_broken_files_name_the_command_that_measures_them(tmp_path):
    rc, readme, page = _docs(tmp_path, {"recon.json": "{not json", "mask.json": {"final": {}}})
    assert rc == 0
    assert readme.count("not measured") == 2  # viewport, sdcost
    assert "run `repaint-nerf bench viewport --json docs/bench/viewport.json`" in readme
    assert "run `repaint-nerf bench sdcost --json docs/bench/sdcost.json`" in readme
    assert "unreadable (JSONDecodeError)" in readme and "unreadable (KeyError" in readme
    assert "Not measured: run `repaint-nerf bench viewport --json docs/bench/viewport.json`" in page


def test_other_bench_files_get_a_section_and_check_reports_staleness(tmp_path):
    rc, _, page = _docs(tmp_path, {"scale_room.json": {"peak_rss_mb": 1234.5, "views": 200, "measured": "2026-12-03"}})
    assert rc == 0 and "## Other: scale_room" in page and "| peak_rss_mb | 1234.500 |" in page
    assert _docs(tmp_path, {}, "--check")[0] == 0, "just written: up to date"
    assert _docs(tmp_path, {"viewport.json": VIEWPORT}, "--check")[0] == 1, "a new JSON: out of date"


def test_a_capture_scale_run_is_tabled_at_its_own_targets(tmp_path):
    sizes = [{"size": 128, "seconds_to_22": 10.0, "seconds_to_24": 40.0, "final_psnr": 25.0},
             {"size": 512, "seconds_to_22": 30.0, "seconds_to_24": 120.0, "final_psnr": 24.5}]
    rc, _, page = _docs(tmp_path, {"scale_capture.json": {"targets": [22.0, 24.0], "sizes": sizes,
                                                          "scene": {"name": "head"}, "measured": "2026-12-05"}})
    section = page.split("## Cost against image size on a real capture")[1]
    assert rc == 0 and "| s to 22 dB | s to 24 dB | x smallest (to 24 dB) |" in section
    assert "| 512 | 30.0 | 120.0 | 3.00 |" in section and "time to 24 dB at 256 px" in section


def test_a_readme_without_markers_is_an_error_that_says_where_the_table_goes(tmp_path, capsys):
    (tmp_path / "README.md").write_text("# no markers\n")
    assert _docs(tmp_path, {})[0] == 2
    assert "figures:begin" in capsys.readouterr().err


def test_bench_stamps_its_json_with_the_date_and_command(tmp_path):
    from repaint_nerf.app.commands.bench import stamp

    out = tmp_path / "r.json"
    out.write_text(json.dumps({"x": 1}))
    stamp(out, ["bench", "recon", "--seconds", "5", "--json", str(out)])
    data = json.loads(out.read_text())
    assert data["x"] == 1 and len(data["measured"]) == 10
    assert data["command"] == f"repaint-nerf bench recon --seconds 5 --json {out}"


def test_the_repository_pages_are_generated_from_docs_bench(monkeypatch):
    """README.md and docs/BENCHMARKS.md are what `repaint-nerf docs` writes from docs/bench/ (not hand-edited)."""
    monkeypatch.chdir(ROOT)
    assert main(["docs", "--check"]) == 0, "run `repaint-nerf docs` and commit the result"
