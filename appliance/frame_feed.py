"""The frame feed between a source's reader thread and the frame loop: the newest frame only
(older ones dropped and counted) for live sources, or every frame in order for lossless ones."""

from __future__ import annotations

import logging
import queue
import threading
import time

from appliance.types import Frame, FrameSource

log = logging.getLogger("roadwatch.service")


class FrameFeed:
    """Reads ``source`` in a thread. ``next(timeout)`` gives the next frame or None; ``done``
    is True once the source ended and every frame was taken."""

    def __init__(self, source: FrameSource, lossless: bool, skip_until: int = 0):
        self.source, self.lossless, self.skip_until = source, lossless, skip_until
        self.eos = False
        self.dropped = 0  # never reset
        self.window_dropped = 0  # reset by the caller for load measurements
        self._q: queue.Queue[Frame] = queue.Queue(maxsize=8)
        self._latest: Frame | None = None
        self._cv = threading.Condition()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="frame-reader", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        """Stop reading and close the source (waits for a read in progress)."""
        self._stop.set()
        self.source.close()
        self._thread.join(timeout=10)

    def _run(self) -> None:
        src = self.source
        while not self._stop.is_set():
            try:
                frame = src.read()
            except Exception:  # noqa: BLE001 - a driver fault must not kill the service
                log.exception("source read failed")
                frame = None
                time.sleep(0.5)
                if getattr(src, "live", True):
                    continue
            if frame is None:
                if getattr(src, "live", False) and not self._stop.is_set():
                    continue
                with self._cv:
                    self.eos = True
                    self._cv.notify_all()
                return
            if frame.seq <= self.skip_until:
                continue
            if self.lossless:
                while not self._stop.is_set():
                    try:
                        self._q.put(frame, timeout=0.2)
                        break
                    except queue.Full:
                        continue
            else:
                with self._cv:
                    if self._latest is not None:
                        self.dropped += 1
                        self.window_dropped += 1
                    self._latest = frame
                    self._cv.notify_all()

    def next(self, timeout: float) -> Frame | None:
        if self.lossless:
            try:
                return self._q.get(timeout=timeout)
            except queue.Empty:
                return None
        with self._cv:
            if self._latest is None and not self.eos:
                self._cv.wait(timeout)
            frame, self._latest = self._latest, None
            return frame

    @property
    def done(self) -> bool:
        if not self.eos:
            return False
        return self._q.empty() if self.lossless else self._latest is None
