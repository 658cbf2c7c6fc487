"""Frame sources: V4L2 cameras, RTSP/HTTP streams, video files and image sequences (OpenCV),
and a synthetic live source, with capture timestamps, timeouts and reconnect with backoff."""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from collections import deque
from pathlib import Path
from typing import Callable
from urllib.parse import parse_qs

import cv2
import numpy as np

from appliance.config import SourceConfig
from appliance.types import Frame

log = logging.getLogger("roadwatch.source")

# Files processed as fast as possible get wall times from this fixed start (2026-01-01T00:00:00Z)
# so that periods line up with the simulator's truth and repeated runs give the same periods.
REPLAY_START_WALL = 1767225600.0


class SourceError(RuntimeError):
    """A source cannot be opened or does not deliver what the configuration asks for."""


# A container clock that steps further than this between two frames is broken (a camera that dropped frames
# steps a few hundred ms at most)
MAX_CLOCK_STEP_S = 2.0


class FileClock:
    """Capture times of a file's frames from its container timestamps (POS_MSEC), counted from the first
    frame's: a camera's recording that dropped frames has gaps there, which a frame counter would close up
    (speeds read high across them, and the clock falls behind). A frame whose timestamp is missing, repeats,
    goes back or steps more than MAX_CLOCK_STEP_S is timed one usual interval (the median of the last steps)
    after the one before, and the clock goes on from there. Without container timestamps (image sequences, a
    rate given by hand) every frame is 1 / fps after the one before."""

    def __init__(self, fps: float, use_container: bool = True):
        self.use_container = use_container
        self.steps: deque[float] = deque([1.0 / fps], maxlen=25)
        self.origin: float | None = None
        self.last = -math.inf

    def next(self, cap: cv2.VideoCapture) -> float:
        """The time (s) of the frame just read from cap."""
        first = not math.isfinite(self.last)
        t = 0.0 if first else self.last + float(np.median(self.steps))
        ms = cap.get(cv2.CAP_PROP_POS_MSEC) if self.use_container else math.nan
        if math.isfinite(ms):
            if self.origin is None:
                self.origin = ms / 1000.0 - t
            pts = ms / 1000.0 - self.origin
            if first or 0.0 < pts - self.last <= MAX_CLOCK_STEP_S:
                if not first:
                    self.steps.append(pts - self.last)
                t = pts
            else:
                self.origin += pts - t
        self.last = t
        return t


def _grey(img: np.ndarray) -> np.ndarray:
    if img.ndim == 3:
        return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    return img


_FFMPEG_OPTIONS_ENV = "OPENCV_FFMPEG_CAPTURE_OPTIONS"
_env_lock = threading.Lock()
_rtsp_working: dict[str, str] = {}  # url -> the RTSP transport that last opened it


def _is_rtsp(url: str) -> bool:
    return url.split("://", 1)[0].lower() in ("rtsp", "rtsps")


def _open_rtsp(url: str, params: list[int]) -> cv2.VideoCapture:
    """Open an RTSP stream, interleaved over TCP first (OpenCV's default, NAT-safe) and then
    RTP over UDP (cameras and servers without TCP support); the transport that worked is tried
    first next time. An operator's own OPENCV_FFMPEG_CAPTURE_OPTIONS is used as it is."""
    if os.environ.get(_FFMPEG_OPTIONS_ENV):
        return cv2.VideoCapture(url, cv2.CAP_FFMPEG, params)
    order = ["tcp", "udp"]
    if _rtsp_working.get(url) == "udp":
        order.reverse()
    cap = None
    for transport in order:
        # OpenCV reads the options from the environment when it opens; set only for this open
        with _env_lock:
            os.environ[_FFMPEG_OPTIONS_ENV] = f"rtsp_transport;{transport}"
            try:
                cap = cv2.VideoCapture(url, cv2.CAP_FFMPEG, params)
            finally:
                os.environ.pop(_FFMPEG_OPTIONS_ENV, None)
        if cap.isOpened():
            _rtsp_working[url] = transport
            return cap
        cap.release()
    return cap


class CaptureSource:
    """Any cv2.VideoCapture: files, image sequences, RTSP/HTTP (FFmpeg backend), V4L2."""

    def __init__(self, url: str, kind: str, cfg: SourceConfig, start_wall: float | None = None):
        self.url, self.kind, self.cfg = url, kind, cfg
        self.live = kind in ("stream", "v4l2")
        self.start_wall = REPLAY_START_WALL if start_wall is None else start_wall
        self.cap: cv2.VideoCapture | None = None
        self.fps = cfg.fps
        self._clock = FileClock(cfg.fps, use_container=False)
        self._seq = 0
        self._t0_mono = 0.0

    def open(self) -> None:
        c = self.cfg
        if self.kind == "v4l2":
            cap = cv2.VideoCapture(self.url, cv2.CAP_V4L2)
            if cap.isOpened():
                if c.pixel_format:
                    cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*c.pixel_format[:4].ljust(4)))
                cap.set(cv2.CAP_PROP_FRAME_WIDTH, c.width)
                cap.set(cv2.CAP_PROP_FRAME_HEIGHT, c.height)
                cap.set(cv2.CAP_PROP_FPS, c.fps)
                cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)
        elif self.kind == "images":
            cap = cv2.VideoCapture(self.url, cv2.CAP_IMAGES)
        else:
            params = [
                cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, int(c.open_timeout_s * 1000),
                cv2.CAP_PROP_READ_TIMEOUT_MSEC, int(c.read_timeout_s * 1000),
            ]
            if _is_rtsp(self.url):
                cap = _open_rtsp(self.url, params)
            else:
                cap = cv2.VideoCapture(self.url, cv2.CAP_FFMPEG, params)
        if not cap.isOpened():
            cap.release()
            raise SourceError(f"source.url: cannot open {self.url!r} ({self.kind})")
        if self.kind == "v4l2":
            self._check_v4l2(cap)
        if self.kind == "file":
            rate = cap.get(cv2.CAP_PROP_FPS)
            if rate and 0 < rate < 1000:
                self.fps = float(rate)
        self.cap = cap
        self._clock = FileClock(self.fps, use_container=self.kind == "file")
        self._t0_mono = time.monotonic()

    def _check_v4l2(self, cap: cv2.VideoCapture) -> None:
        c = self.cfg
        w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        fps = cap.get(cv2.CAP_PROP_FPS)
        if (w, h) != (c.width, c.height):
            cap.release()
            raise SourceError(f"source.width/height: camera {self.url} gives {w}x{h}, config asks {c.width}x{c.height}")
        if fps and abs(fps - c.fps) > 0.5:
            cap.release()
            raise SourceError(f"source.fps: camera {self.url} runs at {fps:g} fps, config asks {c.fps:g}")

    def read(self) -> Frame | None:
        if self.cap is None:
            return None
        ok, img = self.cap.read()
        if not ok or img is None:
            return None
        grey = _grey(img)
        if self.live:
            t, wall = time.monotonic(), time.time()
        else:
            t = self._clock.next(self.cap)
            if self.cfg.realtime:
                delay = self._t0_mono + t - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                t, wall = self._t0_mono + t, time.time()
            else:
                wall = self.start_wall + t
        self._seq += 1
        return Frame(seq=self._seq, t=t, wall=wall, image=grey)

    def close(self) -> None:
        if self.cap is not None:
            self.cap.release()
            self.cap = None


class SyntheticSource:
    """The simulator as a camera: frames from a SceneStream, paced in real time unless
    ``realtime=0`` is given (then as fast as possible, wall time from a fixed start)."""

    def __init__(self, factory: Callable, preset: str, seed: int, cfg: SourceConfig,
                 realtime: bool = True, start_wall: float | None = None):
        self.factory, self.preset, self.seed, self.cfg = factory, preset, seed, cfg
        self.realtime = realtime
        self.start_wall_opt = start_wall
        self.live = realtime
        self.stream = None
        self._pending = None
        self._t0_mono: float | None = None
        self._seq = 0

    def open(self) -> None:
        c = self.cfg
        try:
            self.stream = self.factory(self.preset, self.seed, width=c.width, height=c.height, fps=c.fps)
        except (KeyError, ValueError) as e:
            raise SourceError(f"source.url: synthetic scene {self.preset!r}: {e}") from None
        # Render the first frame now, so the renderer's compilation happens before READY and
        # the real-time clock starts at the first read, not while the service warms up.
        self._pending = self.stream.next_frame()
        self._t0_mono = None
        if self.start_wall_opt is not None:
            self._wall0 = self.start_wall_opt
        else:
            self._wall0 = time.time() if self.realtime else REPLAY_START_WALL

    def read(self) -> Frame | None:
        if self.stream is None:
            return None
        if self._pending is not None:
            (img, ts), self._pending = self._pending, None
        else:
            img, ts = self.stream.next_frame()
        if img is None:
            return None
        if self._t0_mono is None:
            self._t0_mono = time.monotonic() - ts
        if self.realtime:
            delay = self._t0_mono + ts - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            elif delay < -1.0:
                # a stalled camera does not deliver the frames it missed all at once
                self._t0_mono -= delay
        self._seq += 1
        if self.realtime and self.start_wall_opt is None:
            wall = time.time()
        else:
            wall = self._wall0 + ts
        return Frame(seq=self._seq, t=self._t0_mono + ts if self.realtime else float(ts),
                     wall=wall, image=_grey(img))

    def close(self) -> None:
        self.stream = None


class ReconnectingSource:
    """Wraps a source: a live source that fails is reopened with exponential backoff (read()
    blocks meanwhile; ``connected`` tells the service); a looping file starts again at its end."""

    def __init__(self, make: Callable[[], object], cfg: SourceConfig, live: bool, loop: bool = False,
                 realtime: bool | None = None):
        self.make, self.cfg, self.live, self.loop = make, cfg, live, loop
        self.inner = None
        self.connected = False
        self.reconnects = 0
        self._stop = threading.Event()
        self._seq = 0
        self._io = threading.Lock()  # the capture is never released while another thread reads it
        # realtime sources drop frames when processing falls behind; others are processed fully
        self.realtime = (live or cfg.realtime) if realtime is None else realtime

    def _try_open(self) -> bool:
        src = self.make()
        try:
            src.open()
        except SourceError as e:
            log.warning("%s", e)
            return False
        with self._io:
            if self._stop.is_set():
                src.close()
                return False
            self.inner = src
            self.connected = True
        return True

    def open(self) -> None:
        if self.live:
            if not self._try_open():
                log.warning("source not available yet; will keep trying")
            return
        src = self.make()
        src.open()  # a missing file is an error the operator must see
        self.inner, self.connected = src, True

    def read(self) -> Frame | None:
        backoff = 0.5
        while not self._stop.is_set():
            if self.inner is not None:
                with self._io:
                    if self._stop.is_set() or self.inner is None:
                        return None
                    frame = self.inner.read()
                    if frame is not None:
                        if self.live:  # sequence numbers continue across reconnects
                            self._seq += 1
                            frame.seq = self._seq
                        return frame
                    self.inner.close()
                    self.inner = None
                    self.connected = False
                if not self.live and not self.loop:
                    return None
                if self.live:
                    log.warning("source lost: %s", self.cfg.url)
            if self._try_open():
                if self.live:
                    self.reconnects += 1
                    log.info("source reconnected: %s", self.cfg.url)
                backoff = 0.5
                continue
            if not self.live:
                return None
            self._stop.wait(backoff)
            backoff = min(backoff * 2, max(0.5, self.cfg.reconnect_max_s))
        return None

    def close(self) -> None:
        """Stop; waits for a read in progress in another thread (at most the read timeout)."""
        self._stop.set()
        with self._io:
            if self.inner is not None:
                self.inner.close()
                self.inner = None
        self.connected = False


def classify(url: str) -> str:
    if url.startswith("synthetic:"):
        return "synthetic"
    if url.startswith("images:"):
        return "images"
    if url.split("://", 1)[0].lower() in ("rtsp", "rtsps", "http", "https", "rtmp", "udp", "tcp"):
        return "stream"
    if url.startswith("/dev/video") or url.startswith("/dev/v4l/"):
        return "v4l2"
    return "file"


def open_source(cfg: SourceConfig, base_dir: str | os.PathLike | None = None,
                scene_factory: Callable | None = None) -> ReconnectingSource:
    """Build (not yet open) the source for ``source.url``. File paths are relative to
    ``base_dir`` (the config file's directory). ``scene_factory`` makes synthetic scenes
    (tools.simulate.SceneStream); drivers do not import the simulator themselves."""
    url = cfg.url.strip()
    kind = classify(url)
    base = Path(base_dir) if base_dir else Path.cwd()
    if kind == "synthetic":
        if scene_factory is None:
            raise SourceError("source.url: synthetic sources need the simulator (tools.simulate)")
        spec = url[len("synthetic:"):]
        preset, _, query = spec.partition("?")
        q = {k: v[-1] for k, v in parse_qs(query).items()}
        unknown = set(q) - {"seed", "realtime", "start_wall"}
        if unknown:
            raise SourceError(f"source.url: unknown synthetic option(s) {sorted(unknown)} (seed, realtime, start_wall)")
        try:
            seed = int(q.get("seed", 1))
            realtime = q.get("realtime", "1") not in ("0", "false", "no")
            start_wall = float(q["start_wall"]) if "start_wall" in q else None
        except ValueError as e:
            raise SourceError(f"source.url: bad synthetic option in {url!r}: {e}") from None
        if not preset:
            raise SourceError("source.url: 'synthetic:' needs a preset name, e.g. synthetic:free-flow?seed=1")
        return ReconnectingSource(lambda: SyntheticSource(scene_factory, preset, seed, cfg, realtime, start_wall),
                                  cfg, live=False, loop=False, realtime=realtime)
    if kind == "images":
        pattern = url[len("images:"):]
        path = str(base / pattern) if not os.path.isabs(pattern) else pattern
        return ReconnectingSource(lambda: CaptureSource(path, "images", cfg), cfg, live=False, loop=cfg.loop)
    if kind == "file":
        path = Path(url) if os.path.isabs(url) else base / url
        if not path.is_file():
            raise SourceError(f"source.url: video file {str(path)!r} does not exist")
        return ReconnectingSource(lambda: CaptureSource(str(path), "file", cfg), cfg, live=False, loop=cfg.loop)
    return ReconnectingSource(lambda: CaptureSource(url, kind, cfg), cfg, live=True)

