"""`repaint-nerf bench soak`: the editor's worker serves many render requests with camera moves and
cancellations, interleaved with training, and must neither deadlock, crash nor grow in memory.

A simulated UI thread sends bursts of camera moves (each request supersedes the last, so stale renders are
cancelled or dropped), then lets the camera rest until a frame of the newest request arrives (training runs
in the gaps), sometimes pauses training or sends a command. The report has request/frame/cancel counts,
training steps, request-to-frame latency, and RSS at start and end. The worker (app/worker.py) is headless:
no window is opened, so this runs in CI (shorter) and as a benchmark (10,000 requests).
"""
from __future__ import annotations

import argparse
import gc
import json
import random
import tempfile
import time
from pathlib import Path

import numpy as np

HELP = "worker soak: render requests with camera moves/cancellations interleaved with training (RSS, deadlocks)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--requests", type=int, default=10_000, help="render requests to send (default 10000)")
    p.add_argument("--size", type=int, default=16, help="image size of the generated demo scene")
    p.add_argument("--scale", type=float, default=0.5, help="render scale of the requested views")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--deadline", type=float, default=30.0, help="seconds a resting view may wait for its frame")
    p.add_argument("--json", required=True, help="where to write the report")


def _rss_mb() -> float:
    import psutil

    return psutil.Process().memory_info().rss / 2 ** 20


def _small_engine(size: int, root: Path, seed: int):
    """An Engine on a generated demo scene with a small field and batch (the soak tests the plumbing)."""
    from repaint_nerf.core.engine import Engine
    from repaint_nerf.core.field.field import FieldConfig
    from repaint_nerf.core.synth.generate import make_scene
    from repaint_nerf.core.train.stage1 import Stage1Trainer, TrainConfig

    scene_dir = make_scene("demo", root / "demo", size=size, views=6, seed=seed, test_views=1)
    engine = Engine("cpu")
    engine.load(scene_dir, root / "ws")
    cfg = FieldConfig(levels=4, log2_table=12, base_res=8, finest_res=64, hidden=16, geo_feat_dim=7, sh_degree=2,
                      encoding_impl="indexed", compile=False)
    tr = Stage1Trainer(engine.scene, engine.workspace, TrainConfig(rays_per_batch=256, max_samples=64,
                                                                   grid_resolution=16, seed=seed),
                       field_cfg=cfg, device=engine.device)
    engine.trainer, engine.field, engine.grid = tr, tr.field, tr.grid
    return engine


def run_soak(requests: int = 300, size: int = 16, scale: float = 0.5, seed: int = 0, deadline: float = 30.0,
             workdir: str | Path | None = None, progress=None) -> dict:
    """Drive the worker with `requests` render requests; returns the report (see the module docstring).

    'deadlocks' counts resting views whose frame did not come within `deadline` seconds; 'crashes' holds the
    worker's Crashed messages. Raises nothing for those: the caller judges the report.
    """
    from repaint_nerf.app.worker import Crashed, Frame, Reply, Status, Worker

    rng = random.Random(seed)
    tmp = None
    if workdir is None:
        tmp = tempfile.TemporaryDirectory(prefix="soak-")
        workdir = tmp.name
    engine = _small_engine(size, Path(workdir), seed)
    cams = engine.scene.field_cameras("train")
    worker = Worker(engine, target_ms=1000.0, train_budget_s=0.02, rest_s=0.01, preview_interval_s=0.2).start()
    worker.controller.scale = scale
    stats = {"requests": 0, "frames": 0, "final_frames": 0, "rests": 0, "deadlocks": 0, "commands": 0,
             "replies": 0, "status": 0, "pauses": 0}
    crashes: list[str] = []
    sent: dict[int, float] = {}
    answered: set[int] = set()
    latencies: list[float] = []
    last_step = 0
    rss_start = None
    t0 = time.perf_counter()

    def drain() -> None:
        nonlocal last_step
        for msg in worker.poll():
            if isinstance(msg, Frame):
                stats["frames"] += 1
                stats["final_frames"] += int(msg.final)
                if msg.serial not in answered and msg.serial in sent:
                    answered.add(msg.serial)
                    latencies.append((time.perf_counter() - sent[msg.serial]) * 1000.0)
            elif isinstance(msg, Status):
                stats["status"] += 1
                last_step = max(last_step, int(msg.info.get("step", 0) or 0))
            elif isinstance(msg, Reply):
                stats["replies"] += 1
                if msg.error:
                    crashes.append(f"reply {msg.name}: {msg.error}")
            elif isinstance(msg, Crashed):
                crashes.append(f"{msg.where}: {msg.text}")

    try:
        while stats["requests"] < requests and not crashes:
            for _ in range(min(rng.randint(1, 12), requests - stats["requests"])):  # a camera move
                i = rng.randrange(len(cams))
                worker.request_render(cams[i], key=("view", i, stats["requests"]))
                stats["requests"] += 1
                sent[stats["requests"]] = time.perf_counter()  # the worker numbers requests 1, 2, ...
                if rng.random() < 0.5:
                    time.sleep(rng.uniform(0.0, 0.004))
                drain()
            newest = stats["requests"]
            stats["rests"] += 1
            end = time.perf_counter() + deadline
            while newest not in answered and time.perf_counter() < end and not crashes:
                time.sleep(0.002)
                drain()
            if newest not in answered and not crashes:
                stats["deadlocks"] += 1
                break
            time.sleep(rng.uniform(0.0, 0.03))  # the camera rests: the worker trains
            r = rng.random()
            if r < 0.03:
                worker.call(engine.pause)
                worker.call(engine.resume)
                stats["pauses"] += 1
            elif r < 0.06:
                worker.call(engine.info)
                stats["commands"] += 1
            drain()
            if rss_start is None and stats["requests"] >= max(1, requests // 20):
                gc.collect()
                rss_start = _rss_mb()  # after warm-up: caches, allocator pools and first compiles are in
            if progress is not None:
                progress(stats["requests"], requests)
        time.sleep(0.05)
        drain()
        gc.collect()
        rss_end = _rss_mb()
        alive = worker.alive()
    finally:
        worker.stop()
        if tmp is not None:
            tmp.cleanup()
    lat = np.asarray(latencies) if latencies else np.zeros(1)
    rss_start = rss_start if rss_start is not None else rss_end
    cancelled, dropped = worker.cancelled, worker.dropped  # counted by the worker where it cancels or skips
    return {**stats, "cancelled": cancelled, "dropped": dropped, "cancelled_or_dropped": cancelled + dropped,
            "answered": len(answered),
            "train_steps": last_step, "crashes": crashes, "worker_alive": alive,
            "seconds": time.perf_counter() - t0, "latency_ms_p50": float(np.percentile(lat, 50)),
            "latency_ms_p99": float(np.percentile(lat, 99)), "rss_start_mb": rss_start, "rss_end_mb": rss_end,
            "rss_growth_mb": rss_end - rss_start, "size": size, "scale": scale, "seed": seed}


def run(args: argparse.Namespace) -> int:
    """The command: run the soak and write the JSON report; exit 1 on a deadlock, a crash or a dead worker."""
    from repaint_nerf.core.device import describe

    def progress(done: int, total: int) -> None:
        if done % 500 < 12:
            print(f"soak: {done}/{total} requests", flush=True)

    report = run_soak(args.requests, args.size, args.scale, args.seed, args.deadline, progress=progress)
    report["device"] = describe("cpu")
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2) + "\n")
    print(json.dumps({k: v for k, v in report.items() if k != "crashes"}, indent=2))
    ok = not report["deadlocks"] and not report["crashes"] and report["worker_alive"]
    return 0 if ok else 1
