"""Teacher feature codes computed beside stage 1 instead of before it: a background thread runs
`build_feature_store` and hands each image's codes over as they are made, so colour trains from the
first step and each view's feature loss (paper Eq. s1) joins when its codes arrive. A costly teacher
then delays nothing the user sees: the blended ImageNet teacher's 20-43 s per real capture (2 threads)
was all paid before the first step (7-26 s on one thread since core.teachers.projected).
"""
from __future__ import annotations

import atexit
import queue
import threading
import weakref
from typing import Sequence

import cv2
import numpy as np
import torch

from repaint_nerf.core.teachers import cache
from repaint_nerf.core.teachers.base import FeatureTeacher, check_image
from repaint_nerf.core.teachers.cache import FeatureStore
from repaint_nerf.core.teachers.codec import MAX_DIMS, code_size

STREAM_THREADS = 1  # the teacher's share of the CPU: training keeps the rest
_LIVE: "weakref.WeakSet[FeatureStream]" = weakref.WeakSet()


def _code_dims(images, teacher: FeatureTeacher, folder, dims: int, scale: float) -> int:
    """K of the codes the store will hold, before its PCA is fitted: the cached basis's, else what the PCA keeps of
    the teacher's channels (core.teachers.codec.PCACodec.fit), read off one pass over a small copy of an image."""
    codec = cache.stored_codec(images, teacher, folder, dims=dims, scale=scale)
    if codec is not None:
        return codec.dims
    first = check_image(images[0])
    f = 64.0 / max(first.shape[:2])
    small = cv2.resize(first, (max(2, round(first.shape[1] * f)), max(2, round(first.shape[0] * f))),
                       interpolation=cv2.INTER_AREA) if f < 1 else first
    return int(min(dims, np.asarray(teacher(small)).shape[-1], MAX_DIMS))


class _Stopped(Exception):
    """Raised inside the worker thread to stop between images."""


class FeatureStream:
    """A feature store being built on a background thread. The trainer polls it between steps (`poll`);
    `wait` blocks until it is complete (a caller that needs every code at once)."""

    def __init__(self, images: Sequence[np.ndarray], teacher: FeatureTeacher, folder, dims: int,
                 scale: float = 1.0, threads: int = STREAM_THREADS):
        self.dims = _code_dims(images, teacher, folder, int(dims), scale)
        self.sizes = [code_size(np.asarray(im).shape[:2], scale) for im in images]
        self._images, self._teacher, self._folder, self._scale = images, teacher, folder, scale
        self.threads = threads  # the teacher thread's intra-op threads (the trainer leaves them to it)
        self._ready: queue.SimpleQueue = queue.SimpleQueue()
        self._stop = threading.Event()
        self._done = threading.Event()
        self._store: FeatureStore | None = None
        self._error: BaseException | None = None
        self.received = 0  # codes handed over by `poll` so far
        self._thread = threading.Thread(target=self._run, name="feature-teacher", daemon=True)
        self._thread.start()
        _LIVE.add(self)

    def __len__(self) -> int:
        return len(self.sizes)

    def _run(self) -> None:
        torch.set_num_threads(self.threads)  # this thread's intra-op pool only

        def check(done: int, total: int) -> None:
            if self._stop.is_set():
                raise _Stopped

        try:
            self._store = cache.build_feature_store(self._images, self._teacher, self._folder, dims=self.dims,
                                                    scale=self._scale, progress=check,
                                                    on_codes=lambda i, c: self._ready.put((i, c)))
        except _Stopped:
            pass
        except BaseException as exc:  # handed to the polling thread, which reports it
            self._error = exc
        finally:
            self._done.set()

    def poll(self) -> list[tuple[int, torch.Tensor]]:
        """The (image index, (h, w, K) float16 codes) made since the last call; the thread's error, if it
        failed, is raised here, in the caller's thread."""
        out = []
        while True:
            try:
                out.append(self._ready.get_nowait())
            except queue.Empty:
                break
        self.received += len(out)
        if not out and self._error is not None:
            raise self._error
        return out

    @property
    def complete(self) -> bool:
        """Every image's codes have been handed over by `poll`."""
        return self.received == len(self.sizes)

    def wait(self, timeout: float | None = None) -> FeatureStore | None:
        """Block until the thread ends; its store (None when stopped or still running after `timeout`)."""
        self._done.wait(timeout)
        if self._error is not None:
            raise self._error
        return self._store

    def stop(self, wait: float | None = 30.0) -> None:
        """Stop after the image being computed (waiting up to `wait` seconds for it); codes already made stay
        cached for the next open."""
        self._stop.set()
        if wait and self._thread is not threading.current_thread():
            self._thread.join(wait)


@atexit.register
def _stop_all() -> None:
    """A teacher thread still inside a torch call when the interpreter tears down aborts the process."""
    for stream in list(_LIVE):
        stream.stop()

