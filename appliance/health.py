"""Health supervision: turns frame, tracker, channel, storage and load observations into named
faults (HealthFault) with the time each became active, and reports the transitions."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from appliance.config import HealthConfig
from appliance.types import ChannelState, HealthFault, LoopEvent

DARK_HOLD_S = 10.0  # a passing shadow or a headlight flash must not raise TOO_DARK
FIDUCIAL_HOLD_S = 5.0
SHAKE_HOLD_S = 2.0


@dataclass
class Transition:
    fault: HealthFault
    active: bool
    wall: float
    detail: str


class HealthMonitor:
    """Keeps the active faults. Call the observe_* methods, then take ``transitions()``."""

    def __init__(self, cfg: HealthConfig):
        self.cfg = cfg
        self.since: dict[HealthFault, float] = {}  # active fault -> wall time it became active
        self._pending: dict[HealthFault, float] = {}  # condition true since (t), not yet held long enough
        self._transitions: list[Transition] = []
        self._prev_thumb: np.ndarray | None = None
        self._same_since: float | None = None
        self._prev_t = 0.0
        self._last_hit: dict[int, float] = {}
        self._call_since: dict[int, float] = {}
        self.mean_grey = float("nan")

    @property
    def bits(self) -> int:
        out = 0
        for f in self.since:
            out |= 1 << int(f)
        return out

    def names(self) -> list[str]:
        return [f.name for f in sorted(self.since)]

    def active(self, fault: HealthFault) -> bool:
        return fault in self.since

    def transitions(self) -> list[Transition]:
        out, self._transitions = self._transitions, []
        return out

    def set(self, fault: HealthFault, on: bool, t: float, wall: float, detail: str = "", hold_s: float = 0.0) -> None:
        """Raise or clear a fault; it becomes active only once ``on`` held for ``hold_s``."""
        if on:
            first = self._pending.setdefault(fault, t)
            if fault not in self.since and t - first >= hold_s:
                self.since[fault] = wall
                self._transitions.append(Transition(fault, True, wall, detail))
        else:
            self._pending.pop(fault, None)
            if fault in self.since:
                del self.since[fault]
                self._transitions.append(Transition(fault, False, wall, detail))

    def observe_frame(self, t: float, wall: float, image: np.ndarray) -> None:
        """Frozen image and darkness, from a subsampled copy of the frame (cheap)."""
        thumb = image[::8, ::8]
        self.mean_grey = float(thumb.mean())
        if self._prev_thumb is not None and thumb.shape == self._prev_thumb.shape and np.array_equal(thumb, self._prev_thumb):
            if self._same_since is None:
                self._same_since = self._prev_t  # unchanged since the previous frame arrived
        else:
            self._same_since = None
        self._prev_thumb = thumb.copy()
        self._prev_t = t
        frozen = self._same_since is not None and t - self._same_since >= self.cfg.frozen_s
        self.set(HealthFault.FROZEN_IMAGE, frozen, t, wall, "image unchanged")
        self.set(HealthFault.TOO_DARK, self.mean_grey < self.cfg.dark_level, t, wall,
                 f"mean grey {self.mean_grey:.1f}", hold_s=DARK_HOLD_S)
        self.set(HealthFault.CAMERA_LOST, False, t, wall, "frames again")

    def observe_tracker(self, t: float, wall: float, stats: dict) -> None:
        shake = stats.get("shake_px")
        if shake is not None:
            mag = float(np.hypot(*shake)) if isinstance(shake, (tuple, list)) else float(shake)
            self.set(HealthFault.HEAVY_SHAKE, mag > self.cfg.shake_px, t, wall,
                     f"shake {mag:.1f} px", hold_s=SHAKE_HOLD_S)
        total = int(stats.get("fiducials_total") or 0)
        if total > 0:
            ok = int(stats.get("fiducials_ok") or 0)
            self.set(HealthFault.FIDUCIALS_LOST, ok < max(1, (total + 1) // 2), t, wall,
                     f"{ok}/{total} fiducials", hold_s=FIDUCIAL_HOLD_S)

    def observe_channels(self, t: float, wall: float, channels: list[ChannelState], events: list[LoopEvent]) -> None:
        """LOCKED_ON: a call held too long. NO_HITS: a channel without actuations too long."""
        for e in events:
            self._last_hit[e.channel] = t
        locked, silent = [], []
        for ch in channels:
            if ch.call and not ch.forced:
                since = self._call_since.setdefault(ch.channel, t)
                if t - since >= self.cfg.locked_on_s:
                    locked.append(ch.channel)
            else:
                self._call_since.pop(ch.channel, None)
            if t - self._last_hit.setdefault(ch.channel, t) >= self.cfg.no_hits_s:
                silent.append(ch.channel)
        self.set(HealthFault.LOCKED_ON, bool(locked), t, wall, f"channels {locked}")
        self.set(HealthFault.NO_HITS, bool(silent), t, wall, f"channels {silent}")

    def observe_load(self, t: float, wall: float, frames: int, dropped: int) -> None:
        """OVERLOAD when the share of dropped frames over the last window exceeds the limit."""
        total = frames + dropped
        if total < 10:
            return
        pct = 100.0 * dropped / total
        self.set(HealthFault.OVERLOAD, pct > self.cfg.overload_drop_pct, t, wall, f"{pct:.0f}% frames dropped")
