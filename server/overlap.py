"""Offline stages that overlap with tracking: frames read ahead of the tracker, map work done
behind it, each on its own thread.

``track`` is one tracker on one core; reading a frame (PNG and JPEG decoding, the colour's
resampling onto depth) and the map (point cloud fusion, a room keyframe's place features, its
TSDF) cost about as much again. OpenCV and numpy release the GIL in most of that work, so on a
second core it runs beside tracking instead of after it; Open3D's TSDF integration and voxel
downsampling do not (about 4 s of 7scenes_a's map thread holds it), which is why the whole
command gains about 1.2x rather than 2x (benchmarks/track_rate.py). Both stages keep the
order of the frames, so a run's results do not depend on whether they overlap
(``threaded=False`` runs everything in the caller, in the same order: the reference the tests
compare against).
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable, Generator, Iterable
from typing import Any, TypeVar

T = TypeVar("T")
_DONE = object()


def read_ahead(
    items: Iterable[T], ahead: int = 6, threaded: bool = True
) -> Generator[T, None, None]:
    """Yield ``items`` in order, produced up to ``ahead`` items in advance on a thread (each
    item a decoded frame: the bound keeps memory to a few frames). An exception raised while
    producing an item is raised here, where that item would have come. Closing the generator
    early stops the thread."""
    if not threaded:
        yield from items
        return
    slots: queue.Queue[Any] = queue.Queue(maxsize=ahead)
    stop = threading.Event()

    def produce() -> None:
        try:
            for item in items:
                while not stop.is_set():
                    try:
                        slots.put((item, None), timeout=0.1)
                        break
                    except queue.Full:
                        continue
                if stop.is_set():
                    return
            slots.put((_DONE, None))
        except BaseException as exc:  # handed to the consumer, raised there
            slots.put((_DONE, exc))

    thread = threading.Thread(target=produce, name="read-ahead", daemon=True)
    thread.start()
    try:
        while True:
            item, error = slots.get()
            if item is _DONE:
                if error is not None:
                    raise error
                return
            yield item
    finally:
        stop.set()
        while thread.is_alive():  # unblock a producer waiting for a slot
            try:
                slots.get_nowait()
            except queue.Empty:
                thread.join(timeout=0.05)


class Behind:
    """Jobs run in the order given on one thread behind the caller. ``submit`` waits while
    ``limit`` jobs are pending (each holds a frame). The first job that raises stops the rest;
    its exception is raised by the next ``submit`` or by ``join``. ``threaded=False`` runs each
    job inside ``submit``."""

    def __init__(self, limit: int = 8, threaded: bool = True, name: str = "behind") -> None:
        self._error: BaseException | None = None
        self._jobs: queue.Queue[Any] = queue.Queue(maxsize=limit)
        self._thread: threading.Thread | None = None
        if threaded:
            self._thread = threading.Thread(target=self._work, name=name, daemon=True)
            self._thread.start()

    def _work(self) -> None:
        while True:
            job = self._jobs.get()
            if job is _DONE:
                return
            if self._error is None:
                fn, args = job
                try:
                    fn(*args)
                except BaseException as exc:  # raised in the caller's thread
                    self._error = exc

    def submit(self, fn: Callable[..., object], *args: Any) -> None:
        self._raise()
        if self._thread is None:
            fn(*args)
        else:
            self._jobs.put((fn, args))

    def join(self) -> None:
        """Wait until every job ran; raise the first job's exception, if one raised."""
        if self._thread is not None:
            self._jobs.put(_DONE)
            self._thread.join()
            self._thread = None
        self._raise()

    def cancel(self) -> None:
        """Drop the jobs not yet run and stop the thread (the caller is giving up)."""
        if self._thread is not None:
            self._error = self._error or _Cancelled()
            self._jobs.put(_DONE)
            self._thread = None

    def _raise(self) -> None:
        if self._error is not None:
            raise self._error


class _Cancelled(Exception):
    pass
