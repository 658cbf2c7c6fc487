"""The long-running service: the frame loop wiring source → VisionPipeline → TrafficMeasures → store
→ outputs, with health, force-calls, fail-safe, periods, resume and reload."""

# Sources, outputs and the systemd notifier are injected, so the core imports no drivers.

from __future__ import annotations

import logging
import os
import queue
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Protocol

from appliance import checkpoint
from appliance.config import ConfigError, SiteConfig, load_site
from appliance.frame_feed import FrameFeed
from appliance.health import HealthMonitor
from appliance.store import Store, is_disk_full, period_from_row
from appliance.types import (ChannelState, DetectorSnapshot, Frame, FrameSource, HealthFault, LaneAggregate,
                             LoopEvent, Output, VehicleRecord)

log = logging.getLogger("roadwatch.service")

# Faults under which the detector cannot see traffic: channels go to the configured fail-safe.
FAILSAFE_FAULTS = (HealthFault.CAMERA_LOST, HealthFault.FROZEN_IMAGE, HealthFault.OVERLOAD)
STATE_SAVE_S = 2.0  # how often the period in progress is saved (bounds what a power cut loses)
STORE_RETRY_S = 10.0
PRUNE_EVERY_S = 3600.0
IDLE_PUBLISH_S = 0.2
MAX_PENDING_ROWS = 200_000  # bound the memory used while the disk is full
LOAD_WINDOW_S = 10.0


class Notifier(Protocol):
    def ready(self, status: str = "") -> bool: ...

    def watchdog(self) -> bool: ...

    def status(self, text: str) -> bool: ...

    def stopping(self) -> bool: ...


class _NullNotifier:
    def ready(self, status: str = "") -> bool:
        return False

    def watchdog(self) -> bool:
        return False

    def status(self, text: str) -> bool:
        return False

    def stopping(self) -> bool:
        return False


@dataclass
class ServiceHooks:
    """How the service gets its driver-side parts (injected by tools/)."""

    make_source: Callable[[SiteConfig], FrameSource]
    make_outputs: Callable[[SiteConfig], list[Output]] = lambda site: []
    notifier: Notifier = field(default_factory=_NullNotifier)
    make_pipeline: Callable[[SiteConfig], Any] | None = None
    make_measures: Callable[[SiteConfig], Any] | None = None
    before_stop: Callable[["Service"], None] | None = None  # called with outputs still serving


def _default_pipeline(site: SiteConfig):
    from appliance.pipeline import VisionPipeline

    return VisionPipeline(site)


def _default_measures(site: SiteConfig):
    from appliance.measures import TrafficMeasures

    return TrafficMeasures(site)


def _same(a: SiteConfig, b: SiteConfig, *sections: str) -> bool:
    return all(a.raw.get(s) == b.raw.get(s) for s in sections)


class Service:
    """One detector. ``run()`` blocks until ``stop()`` (or end of a file source)."""

    def __init__(self, site: SiteConfig, hooks: ServiceHooks, version: str = "", store_path: str | None = None):
        self.site = site
        self.hooks = hooks
        self.version = version
        self.notifier = hooks.notifier
        self._store_path_override = store_path
        self.store: Store | None = None
        self.source: FrameSource | None = None
        self.outputs: list[Output] = []
        self.pipeline = None
        self.measures = None
        self.health = HealthMonitor(site.health)
        self.started_mono = time.monotonic()
        self.frames = 0
        self.fps = 0.0
        self.period_seq = 0
        self.last_period: list[LaneAggregate] = []
        self.last_period_start: float | None = None
        self.last_snapshot: DetectorSnapshot | None = None
        self.last_frame: Frame | None = None
        self.tracked = 0
        self._stop = threading.Event()
        self._reload_flag = threading.Event()
        self._reload_requests: queue.Queue = queue.Queue()
        self._forced: dict[int, float] = {}  # channel -> monotonic time the forced call ends
        self._lock = threading.RLock()  # pipeline (overlay from the status thread) and snapshot
        self.feed: FrameFeed | None = None
        self._pending_periods: list[LaneAggregate] = []
        self._pending_events: list[LoopEvent] = []
        self._pending_vehicles: list[VehicleRecord] = []
        self._pending_health: list[tuple] = []
        self._last_store_try = 0.0
        self._last_state_save = 0.0
        self._last_prune = time.monotonic() - PRUNE_EVERY_S + 60.0  # first pruning a minute after start
        self._last_frame_mono = time.monotonic()
        self._fps_window: list[float] = []
        self._load = [time.monotonic(), 0]  # window start, frames
        self._last_status = 0.0
        self._last_watchdog = 0.0
        self.lossless = False
        self.ready = False
        self._skip_until = 0  # frames up to this seq were processed before a restart
        self._resumed_from_checkpoint = False

    # ---------------------------------------------------------------- commands (any thread)

    @property
    def allow_commands(self) -> bool:
        return self.site.status.allow_commands

    def stop(self) -> None:
        self._stop.set()

    def request_reload(self) -> None:
        """From a signal handler (SIGHUP): reload the config file at the next frame."""
        self._reload_flag.set()

    def force_call(self, channel: int, seconds: float) -> None:
        """Force a channel's call on for ``seconds`` (clamped to outputs.force_call_max_s); 0 cancels."""
        if channel not in self.site.loop_by_channel():
            raise ValueError(f"no detector channel {channel} (channels: {sorted(self.site.loop_by_channel())})")
        seconds = max(0.0, min(float(seconds), self.site.outputs.force_call_max_s))
        with self._lock:
            if seconds == 0:
                self._forced.pop(channel, None)
            else:
                self._forced[channel] = time.monotonic() + seconds
        log.info("force call channel %d for %.1f s", channel, seconds)

    def reload(self, timeout: float = 60.0) -> None:
        """Re-read the config file; raises ConfigError (the running config stays) if it is invalid."""
        if not self.site.path:
            raise ValueError("this site was not loaded from a file; nothing to reload")
        new = load_site(self.site.path)
        done = threading.Event()
        box: dict = {}
        self._reload_requests.put((new, done, box))
        if not done.wait(timeout):
            raise ValueError("reload timed out")
        if "error" in box:
            raise ValueError(box["error"])

    # ---------------------------------------------------------------- status (any thread)

    def status(self) -> dict:
        snap = self.last_snapshot
        lanes = {}
        if self.measures is not None:
            with self._lock:
                lanes = {str(k): v for k, v in self.measures.live_lane_counts().items()}
        return {
            "site": self.site.site.name,
            "version": self.version,
            "uptime_s": round(time.monotonic() - self.started_mono, 1),
            "fps": round(self.fps, 2),
            "dropped_frames": self.dropped,
            "frames": self.frames,
            # faults and channels from the same published snapshot, so they never disagree
            "faults": [f.name for f in HealthFault if snap.has_fault(f)] if snap else self.health.names(),
            "fault_bits": snap.faults if snap else self.health.bits,
            "tracked_vehicles": self.tracked,
            "period_seq": self.period_seq,
            "channels": [asdict(c) for c in (snap.channels if snap else [])],
            "lanes": lanes,
            "last_period": [a.to_dict() for a in self.last_period],
            "config_path": self.site.path,
            "pid": os.getpid(),
            "ready": self.ready,
            "store": str(self.store.path) if self.store else None,
        }

    def snapshot_png(self, overlay: bool = True) -> bytes | None:
        import cv2

        frame = self.last_frame
        if frame is None:
            return None
        img = frame.image
        if overlay and self.pipeline is not None:
            with self._lock:
                img = self.pipeline.overlay(img)
        ok, buf = cv2.imencode(".png", img)
        return buf.tobytes() if ok else None

    # ---------------------------------------------------------------- start / stop

    def start(self) -> None:
        """Open store, source and outputs, warm up the pipeline; then READY=1."""
        self._open_store()
        self.measures = (self.hooks.make_measures or _default_measures)(self.site)
        self.pipeline = (self.hooks.make_pipeline or _default_pipeline)(self.site)
        self._open_source()
        self._resume()
        self._start_outputs()
        t0 = time.monotonic()
        self.pipeline.warmup()
        log.info("pipeline warmed up in %.1f s", time.monotonic() - t0)
        self._start_reader()
        self.ready = True
        self.notifier.ready("started")
        log.info("ready: site %r, source %s, %d output(s)", self.site.site.name, self.site.source.url, len(self.outputs))

    def _store_path(self) -> Path:
        p = Path(self._store_path_override or self.site.store.path)
        if not p.is_absolute() and self.site.path:
            p = Path(self.site.path).resolve().parent / p
        return p

    def _open_store(self) -> None:
        self.store = Store(self._store_path())
        log.info("store %s (schema %d)", self.store.path, self.store.schema_version())

    def _open_source(self) -> None:
        self.source = self.hooks.make_source(self.site)
        self.source.open()
        self.lossless = not getattr(self.source, "realtime", True)

    def _start_outputs(self) -> None:
        self.outputs = list(self.hooks.make_outputs(self.site))
        for out in self.outputs:
            out.start(self)

    def _resume(self) -> None:
        """Period sequence and last period always carry over. A lossless (file) source is
        reprocessed from its start, so nothing else is restored (all writes are idempotent);
        a live source resumes the saved period in progress, which is then marked partial."""
        st = self.store
        self.period_seq = int(st.load_state("period_seq", 0))
        self.last_period_start = st.load_state("last_period_start", None)
        if self.last_period_start is not None:
            rows = st.periods(self.last_period_start, self.last_period_start + 1e-6)
            self.last_period = [period_from_row(r) for r in rows]
        if self.lossless:
            self._load_checkpoint()
            return
        saved = st.load_state("measures", None)
        if not saved:
            return
        try:
            if saved.get("lanes_key") != self._lanes_key():
                log.info("saved period state is for other lanes; not resumed")
                return
            now_wall = time.time()
            if saved["state"].get("now_wall") and now_wall - saved["state"]["now_wall"] < self.site.measures.period_s:
                self.measures.restore(saved["state"])
                log.info("resumed the period in progress (marked partial)")
            else:
                old = (self.hooks.make_measures or _default_measures)(self.site)
                old.restore(saved["state"])
                partial = old.flush(saved["state"].get("now_wall") or now_wall)
                self._store_periods(partial, publish=False)
                log.info("wrote the interrupted period as partial")
        except (ValueError, KeyError, TypeError) as e:
            log.warning("saved period state not usable (%s); starting a fresh period", e)

    def _checkpoint_key(self) -> list:
        return [self.site.source.url, self._lanes_key(), self.site.raw.get("tracking"), self.site.raw.get("fiducials")]

    def _save_checkpoint(self, frame: Frame) -> None:
        """Lossless (file) sources: the whole tracker and measures state at a period boundary,
        so a restart after a crash continues exactly where this frame left off."""
        self.store.save_blob("checkpoint", checkpoint.pack(self._checkpoint_key(), frame.seq, self.frames,
                                                           self.pipeline, self.measures))

    def _load_checkpoint(self) -> None:
        ck = checkpoint.unpack(self.store.load_blob("checkpoint"), self._checkpoint_key())
        if ck is None:
            return
        self.pipeline, self.measures = ck["pipeline"], ck["measures"]
        self._resumed_from_checkpoint = True
        self._skip_until = int(ck["seq"])
        self.frames = int(ck["frames"])
        log.info("resuming after frame %d (last completed period)", self._skip_until)

    def _lanes_key(self) -> list:
        return [self.site.raw.get(k) for k in ("lanes", "loops", "measures", "calibration")]

    def _start_reader(self) -> None:
        self.feed = FrameFeed(self.source, self.lossless, self._skip_until)
        self.feed.start()

    def _stop_reader(self) -> None:
        if self.feed is not None:
            self.feed.stop()
        elif self.source is not None:
            self.source.close()

    @property
    def dropped(self) -> int:
        return self.feed.dropped if self.feed is not None else 0

    def shutdown(self) -> None:
        """Clean stop: the partial period is written, state saved, outputs stopped."""
        self.notifier.stopping()
        self._stop_reader()
        if self.measures is not None and self.store is not None:
            wall = self.last_frame.wall if self.last_frame is not None else time.time()
            partial = self.measures.flush(wall)
            self._store_periods(partial, publish=False)
            self._flush_detail()
            self._save_state(force=True)
        for out in self.outputs:
            try:
                out.stop()
            except Exception:  # noqa: BLE001 - stopping must reach every output
                log.exception("stopping output %r", out)
        self.outputs = []
        if self.store is not None:
            self.store.close()
            self.store = None
        log.info("stopped after %d frames (%d dropped)", self.frames, self.dropped)

    # ---------------------------------------------------------------- the loop

    def run(self, max_seconds: float | None = None) -> None:
        """Start, loop until stop() / end of a file / max_seconds, then shut down cleanly."""
        try:
            self.start()
            deadline = None if max_seconds is None else time.monotonic() + max_seconds
            while not self._stop.is_set():
                if deadline is not None and time.monotonic() >= deadline:
                    break
                self._handle_reloads()
                frame = self.feed.next(IDLE_PUBLISH_S)
                if frame is None:
                    if self.feed.done:
                        log.info("end of source")
                        break
                    self._idle()
                    continue
                self._process(frame)
            if self.hooks.before_stop is not None:
                self.hooks.before_stop(self)
        except Exception:
            if self._resumed_from_checkpoint and self.store is not None:
                # a checkpoint that cannot be continued must not make every restart fail
                log.error("processing failed after resuming from a checkpoint; the checkpoint is discarded")
                self.store.save_state("checkpoint", None)
            raise
        finally:
            self.shutdown()

    def _process(self, frame: Frame) -> None:
        now = time.monotonic()
        self._last_frame_mono = now
        self.last_frame = frame
        self.frames += 1
        self._load[1] += 1
        self._fps_window.append(now)
        while self._fps_window and now - self._fps_window[0] > 2.0:
            self._fps_window.pop(0)
        if len(self._fps_window) > 1:
            self.fps = (len(self._fps_window) - 1) / max(1e-6, self._fps_window[-1] - self._fps_window[0])
        with self._lock:
            try:
                vehicles = self.pipeline.step(frame)
            except ValueError as e:  # a frame the pipeline cannot take (size, type): skip it, say why
                if not self.health.active(HealthFault.CONFIG):
                    log.error("frame rejected: %s", e)
                self.health.set(HealthFault.CONFIG, True, frame.t, frame.wall, str(e))
                self._record_health(frame.wall)
                self._publish(frame.wall, self.measures.channels(), [])
                self._housekeeping(now)
                return
            if self.health.active(HealthFault.CONFIG):
                self.health.set(HealthFault.CONFIG, False, frame.t, frame.wall, "frames accepted again")
            upd = self.measures.step(frame.t, frame.wall, vehicles, getattr(self.pipeline, "loop_sights", None))
            channels = self.measures.channels()
        self.tracked = sum(1 for v in vehicles if not v.finished)
        h = self.health
        h.observe_frame(frame.t, frame.wall, frame.image)
        h.observe_tracker(frame.t, frame.wall, getattr(self.pipeline, "stats", {}) or {})
        h.observe_channels(frame.t, frame.wall, channels, upd.loop_events)
        if now - self._load[0] >= LOAD_WINDOW_S:
            h.observe_load(frame.t, frame.wall, self._load[1], self.feed.window_dropped)
            self._load = [now, 0]
            self.feed.window_dropped = 0
        self._pending_events.extend(upd.loop_events)
        self._pending_vehicles.extend(upd.vehicles)
        if upd.periods:
            self._store_periods(upd.periods, publish=True)
            self._flush_detail()
            if self.lossless and not self.health.active(HealthFault.STORAGE):
                try:
                    self._save_checkpoint(frame)
                except Exception as e:  # noqa: BLE001
                    self._storage_failed(e)
        self._record_health(frame.wall)
        self._flush_detail()
        self._save_state()
        self._publish(frame.wall, channels, upd.loop_events)
        self._housekeeping(now)

    def _idle(self) -> None:
        """No frame this tick: camera-lost detection, fail-safe publishing, watchdog."""
        now = time.monotonic()
        wall = time.time()
        connected = getattr(self.source, "connected", True)
        lost = (not connected) or (now - self._last_frame_mono > self.site.source.read_timeout_s)
        if lost and not self.lossless:
            self.health.set(HealthFault.CAMERA_LOST, True, now, wall, f"no frames from {self.site.source.url}")
        self._record_health(wall)
        with self._lock:
            channels = self.measures.channels()
        self._publish(wall, channels, [])
        self._housekeeping(now)

    def _housekeeping(self, now: float) -> None:
        if now - self._last_watchdog >= 0.5:
            self.notifier.watchdog()
            self._last_watchdog = now
        if now - self._last_status >= 5.0:
            faults = ",".join(self.health.names()) or "none"
            self.notifier.status(f"fps {self.fps:.1f}, vehicles {self.tracked}, dropped {self.dropped}, faults {faults}")
            self._last_status = now
        if (self._pending_periods or self._pending_events or self._pending_vehicles or self._pending_health) \
                and now - self._last_store_try >= STORE_RETRY_S:
            self._retry_store()
        if now - self._last_prune >= PRUNE_EVERY_S and self.store is not None:
            self._last_prune = now
            threading.Thread(target=self._prune, name="store-prune", daemon=True).start()

    def _prune(self) -> None:
        try:
            st = Store(self._store_path())
            n = st.prune(self.site.store.retention_days, self.site.store.max_mb)
            st.close()
            if n:
                log.info("pruned %d old rows from the store", n)
        except Exception as e:  # noqa: BLE001 - pruning is best effort
            log.warning("store pruning failed: %s", e)

    # ---------------------------------------------------------------- snapshot

    def _publish(self, wall: float, channels: list[ChannelState], events: list[LoopEvent]) -> None:
        snap = self.build_snapshot(wall, channels)
        self.last_snapshot = snap
        for out in self.outputs:
            try:
                out.publish(snap, events)
            except Exception:  # noqa: BLE001 - one output must not stop the others
                log.exception("output %r failed to publish", out)

    def build_snapshot(self, wall: float, channels: list[ChannelState]) -> DetectorSnapshot:
        """Channels with force-calls and the fail-safe applied, plus health and the last period."""
        now = time.monotonic()
        failsafe = any(self.health.active(f) for f in FAILSAFE_FAULTS)
        fs_call = self.site.outputs.failsafe == "call"
        with self._lock:
            self._forced = {ch: until for ch, until in self._forced.items() if until > now}
            forced = dict(self._forced)
        out = []
        for ch in channels:
            c = ChannelState(ch.channel, ch.loop_id, ch.lane, ch.call, ch.count, ch.occupancy_pct,
                             ch.last_speed_kmh, ch.last_length_m, dict(ch.class_counts), ch.forced)
            if failsafe:
                c.call = fs_call
            if c.channel in forced:
                c.call, c.forced = True, True
            out.append(c)
        return DetectorSnapshot(
            wall=wall, uptime_s=now - self.started_mono, channels=out, faults=self.health.bits,
            fps=self.fps, last_period=list(self.last_period), period_seq=self.period_seq,
            tracked_vehicles=self.tracked, dropped_frames=self.dropped,
        )

    # ---------------------------------------------------------------- storage

    def _store_periods(self, periods: list[LaneAggregate], publish: bool) -> None:
        """Commit completed periods durably; only then do they become the published last period."""
        if not periods:
            return
        try:
            self.store.write_periods(periods)
            self._storage_ok()
        except Exception as e:  # noqa: BLE001 - sqlite3 errors and OSError alike
            self._storage_failed(e)
            self._pending_periods.extend(periods)
        if not publish:
            return
        by_start: dict[float, list[LaneAggregate]] = {}
        for a in periods:
            by_start.setdefault(a.period_start, []).append(a)
        for start in sorted(by_start):
            if self.last_period_start is None or start > self.last_period_start:
                self.period_seq = (self.period_seq + 1) % 256
                self.last_period_start = start
                self.last_period = by_start[start]
        self._save_state(force=True)

    def _flush_detail(self) -> None:
        if not (self._pending_events or self._pending_vehicles):
            return
        if self.health.active(HealthFault.STORAGE):
            self._bound_pending()
            return
        try:
            self.store.write_loop_events(self._pending_events)
            self.store.write_vehicles(self._pending_vehicles, trajectories=self.site.store.trajectories)
            self._pending_events, self._pending_vehicles = [], []
        except Exception as e:  # noqa: BLE001
            self._storage_failed(e)
            self._bound_pending()

    def _bound_pending(self) -> None:
        for name in ("_pending_events", "_pending_vehicles"):
            lst = getattr(self, name)
            if len(lst) > MAX_PENDING_ROWS:
                del lst[: len(lst) - MAX_PENDING_ROWS]

    def _record_health(self, wall: float) -> None:
        for tr in self.health.transitions():
            level = logging.WARNING if tr.active else logging.INFO
            log.log(level, "fault %s %s (%s)", tr.fault.name, "raised" if tr.active else "cleared", tr.detail)
            self._pending_health.append((tr.wall, tr.fault.name, tr.active, tr.detail))
        if self._pending_health and not self.health.active(HealthFault.STORAGE):
            try:
                for row in self._pending_health:
                    self.store.write_health(*row)
                self._pending_health = []
            except Exception as e:  # noqa: BLE001
                self._storage_failed(e)

    def _save_state(self, force: bool = False) -> None:
        now = time.monotonic()
        if not force and now - self._last_state_save < STATE_SAVE_S:
            return
        if self.health.active(HealthFault.STORAGE) and not force:
            return
        self._last_state_save = now
        try:
            self.store.save_state("period_seq", self.period_seq)
            self.store.save_state("last_period_start", self.last_period_start)
            if not self.lossless:
                with self._lock:
                    self.store.save_state("measures", {"lanes_key": self._lanes_key(), "state": self.measures.state()})
        except Exception as e:  # noqa: BLE001
            self._storage_failed(e)

    def _storage_failed(self, e: BaseException) -> None:
        self._last_store_try = time.monotonic()
        if not self.health.active(HealthFault.STORAGE):
            kind = "disk full" if is_disk_full(e) else "error"
            self.health.set(HealthFault.STORAGE, True, time.monotonic(), time.time(), f"{kind}: {e}")
            log.error("storage %s: %s (live data continues; will retry)", "disk full" if is_disk_full(e) else "failure", e)

    def _storage_ok(self) -> None:
        if self.health.active(HealthFault.STORAGE):
            self.health.set(HealthFault.STORAGE, False, time.monotonic(), time.time(), "storage works again")

    def _retry_store(self) -> None:
        self._last_store_try = time.monotonic()
        try:
            if self._pending_periods:
                self.store.write_periods(self._pending_periods)
                self._pending_periods = []
            self.store.write_loop_events(self._pending_events)
            self.store.write_vehicles(self._pending_vehicles, trajectories=self.site.store.trajectories)
            self._pending_events, self._pending_vehicles = [], []
            self._storage_ok()
            self._record_health(time.time())
            self._save_state(force=True)
        except Exception as e:  # noqa: BLE001
            self._storage_failed(e)

    # ---------------------------------------------------------------- reload

    def _handle_reloads(self) -> None:
        if self._reload_flag.is_set():
            self._reload_flag.clear()
            try:
                new = load_site(self.site.path) if self.site.path else None
            except ConfigError as e:
                log.error("reload refused, keeping the running config: %s", e)
                new = None
            if new is not None:
                self._apply(new)
        while True:
            try:
                new, done, box = self._reload_requests.get_nowait()
            except queue.Empty:
                return
            try:
                self._apply(new)
            except Exception as e:  # noqa: BLE001 - reported to the caller
                log.exception("reload failed")
                box["error"] = f"reload failed: {e}"
            done.set()

    def _apply(self, new: SiteConfig) -> None:
        """Switch to a new validated config, keeping what did not change."""
        old = self.site
        keep_measures = _same(old, new, "lanes", "loops", "measures", "calibration")
        keep_pipeline = _same(old, new, "lanes", "calibration", "fiducials", "tracking", "source")
        keep_source = _same(old, new, "source")
        keep_outputs = _same(old, new, "outputs", "loops")
        old_store = self._store_path()
        self.site = new
        new_store = self._store_path() != old_store
        self.health.cfg = new.health
        if not keep_source:
            self._stop_reader()
            self._open_source()
            self._start_reader()
        if new_store:
            self.store.close()
            self._open_store()
        with self._lock:
            if not keep_measures:
                partial = self.measures.flush(self.last_frame.wall if self.last_frame else time.time())
                self._store_periods(partial, publish=False)
                self.measures = (self.hooks.make_measures or _default_measures)(new)
            if not keep_pipeline:
                self.pipeline = (self.hooks.make_pipeline or _default_pipeline)(new)
                self.pipeline.warmup()
            elif not _same(old, new, "loops") and hasattr(self.pipeline, "watch_loops"):
                self.pipeline.watch_loops(new)  # the loops' patches of the image, where they are now
        if not keep_outputs:
            for out in self.outputs:
                out.stop()
            self._start_outputs()
        log.info("config reloaded from %s (period state %s)", new.path, "kept" if keep_measures else "restarted")

