"""Virtual loops: presence/pulse call, actuation events, counts, occupancy, speed, length class."""

from __future__ import annotations

import bisect
from dataclasses import dataclass, field

import numpy as np

from appliance.config import LoopConfig, MeasuresConfig
from appliance.types import ChannelState, LoopEvent, LoopSight

# A loop free for less than this between two presences gave one actuation: the second is a fragment of
# the same vehicle (a group that came apart, a length estimate that shrank and grew). Vehicles a real loop
# separates leave it free for far longer: 1.16 s at the least in the dense synthetic scene, and 0.2 s is
# 2 m at 36 km/h, a gap nobody keeps. The call is held through such a dropout, as a detector card's
# dropout filter holds it, so that a controller counting call edges does not count the fragment either.
BRIDGE_S = 0.2
STANDING = -1  # the id a standing call seen in the image (appliance.presence) is held under
# A vehicle that left the loop crawling (below CRAWL_MPS, or lost there) while the image shows the loop
# occupied since before that may be stopping on it, its track lost as it stopped: the actuation waits up to
# WAIT_S for a standing call to take it on, so that the call does not drop and come back (which a controller
# counting call edges would count twice). A vehicle that stood within SETTLE_S of the loop's last actuation
# ending is taken to be its vehicle; the image calls it standing 1.5 s after it stood (appliance.presence),
# hence the longer wait. A vehicle coming onto the loop ends the wait. One that drove off at speed does not
# wait: the patch may still show it (a tall body over the road behind it) as a follower arrives, whose call
# edge a controller must see.
SETTLE_S = 3.0
WAIT_S = 5.0
CRAWL_MPS = 3.0
# The loop's last vehicle, tracked crawling or standing just past it on the camera's side (lower Y: the
# near side, where an approaching queue stops), hides the loop's patch under its body in the image (a van's
# roof is seen over the road metres behind it): the image's standing call seen then is its body, not a vehicle
# on the loop, and is refused for as long as it lasts while the tracker follows that vehicle (standing, or
# driving off before the image lets the call go). If its track is lost, nothing says what stands on the loop
# now (in a queue, the next car, its features lost too): the call is taken, from when it stood.
HIDDEN_BEHIND_M = 6.0  # its far end at most this far short of the loop
HIDDEN_STALE_S = 0.2  # ... as tracked this recently


def length_class(length_m: float | None, measures: MeasuresConfig) -> str | None:
    """IRIS-style length bin name (``measures.length_class_bounds_m``/``_names``)."""
    if length_m is None or not np.isfinite(length_m):
        return None
    return measures.length_class_names[bisect.bisect_right(measures.length_class_bounds_m, length_m)]


def _below(a: float, b: float, c: float) -> tuple[float, float]:
    """s-interval within [0, 1] where a + (b - a) s <= c."""
    if abs(b - a) < 1e-12:
        return (0.0, 1.0) if a <= c else (1.0, 0.0)
    s = (c - a) / (b - a)
    return (0.0, min(1.0, s)) if b > a else (max(0.0, s), 1.0)


def overlap_interval(
    lo0: float, hi0: float, lo1: float, hi1: float, y0: float, y1: float
) -> tuple[float, float] | None:
    """Fraction [sa, sb] of a step during which body [lo, hi] (moving linearly) overlaps [y0, y1]."""
    a1, b1 = _below(lo0, lo1, y1)  # lo <= y1
    a2, b2 = _below(-hi0, -hi1, -y0)  # hi >= y0
    a, b = max(a1, a2), min(b1, b2)
    return (a, b) if b >= a else None


def union_length(intervals: list[tuple[float, float]], w0: float, w1: float) -> float:
    """Length of the union of intervals clipped to [w0, w1]."""
    clipped = sorted((max(a, w0), min(b, w1)) for a, b in intervals if b > w0 and a < w1)
    total, end = 0.0, -np.inf
    for a, b in clipped:
        if b <= end:
            continue
        total += b - max(a, end)
        end = b
    return total


@dataclass
class _Presence:
    t_on: float
    wall_on: float
    speeds: list[float] = field(default_factory=list)
    length: float | None = None


class VirtualLoop:
    """One loop in one lane, spanning [y0, y1] along the road."""

    def __init__(self, cfg: LoopConfig, measures: MeasuresConfig) -> None:
        self.cfg = cfg
        self.measures = measures
        self.y0 = float(cfg.y_m)
        self.y1 = float(cfg.y_m + cfg.length_m)
        self.active: dict[int, _Presence] = {}
        self.count = 0
        self.class_counts: dict[str, int] = {}
        self.last_speed: float | None = None
        self.last_length: float | None = None
        self.last_on_wall: float | None = None
        self.intervals: list[tuple[float, float]] = []  # closed on-intervals (wall), pruned
        self.on_times: dict[int, float] = {}  # vehicle -> t_on, for speed traps
        self.left: set[int] = set()  # vehicles that have been over the loop and left it: they are behind it
        self.partner: VirtualLoop | None = None
        self.now_wall: float | None = None
        # the actuation in progress: vehicles overlapping on the loop give one actuation, as a real
        # loop gives (a fragment of a vehicle does not add a count)
        self.act: dict | None = None
        self.last_off: float | None = None  # capture time the last actuation ended ...
        self.last_crawled = False  # ... and whether its last vehicle left crawling (or was lost on the loop)
        # ... that vehicle, and its latest (t, lo, hi, speed); and the standing call refused as its body
        self.last_left: tuple[int, tuple | None] = (STANDING, None)
        self.hid: tuple[float, float] | None = None

    def update(
        self, vid: int, in_lane: bool, prev: tuple | None, cur: tuple, offset: float, was_in_lane: bool = True
    ) -> list[LoopEvent]:
        """Advance one vehicle by one step. prev/cur = (t, lo, hi, speed, length); offset = wall - t.

        A vehicle that came into the lane during the step (lane change) is on from the step's end.
        Returns the actuations that ended.
        """
        t1, lo1, hi1, v1, len1 = cur
        if vid == self.last_left[0]:
            self.last_left = (vid, (t1, lo1, hi1, abs(v1)))
        if prev is None:
            t0, lo0, hi0 = t1, lo1, hi1
        else:
            t0, lo0, hi0 = prev[0], prev[1], prev[2]
        span = overlap_interval(lo0, hi0, lo1, hi1, self.y0, self.y1) if in_lane else None
        p = self.active.get(vid)
        dt = t1 - t0
        out: list[LoopEvent] = []
        if p is None:
            if span is None:
                return out
            t_on = t0 + span[0] * dt if was_in_lane else t1
            if list(self.active) == [STANDING] and abs(v1) >= CRAWL_MPS and vid not in self.left:
                # nobody drives onto a loop through a vehicle standing on it: the image's standing call is one
                # the queue's bodies give, hiding the loop; this vehicle is a new actuation (the call stays on)
                self._close(STANDING, t_on)
                ev = self._emit()
            else:
                ev = self.tick(t_on)  # the loop was free long enough: the last actuation is over
            if ev is not None:
                out.append(ev)
            p = self.active[vid] = _Presence(t_on, t_on + offset)
            self.on_times[vid] = t_on
            if self.act is None:
                # a vehicle passes a point once: one that left the loop and is back on it is the same vehicle,
                # its extent misjudged for a while; the loop is occupied again, the vehicle not counted again
                self._start(vid, t_on, offset, counted=vid not in self.left)
        if span is not None:
            p.speeds.append(v1)
            p.length = len1
            if span[1] >= 1.0:
                return out
            t_off = t0 + span[1] * dt
        else:
            t_off = t0
        ev = self._close(vid, t_off)
        return out + ([ev] if ev is not None else [])

    def hold(self, t: float, offset: float, sight: LoopSight | None) -> LoopEvent | None:
        """A vehicle seen in the image standing on the loop holds it on, tracked or not (a queued vehicle's
        features are often lost). With the tracker's vehicles on the loop it is part of their actuation. If it
        is the vehicle the loop saw last, the call goes on again where that one's went off (if it went off), and
        it is not counted again; else it goes on when it stood, and it is counted. A call seen while the loop's
        last vehicle hides the loop is refused while it lasts and that vehicle is tracked (see HIDDEN_BEHIND_M);
        a vehicle the tracker puts on the loop meanwhile takes it on as above."""
        standing = sight.standing if sight is not None else None
        if standing is None:
            return self._close(STANDING, t) if STANDING in self.active else None
        if STANDING in self.active:
            return None
        came, stood = standing
        if self.act is not None and self.active:  # on the loop with the tracker's vehicles: the same actuation
            t_on = max(came, self.act["t_on"])
            self.active[STANDING] = _Presence(t_on, t_on + offset)
            return None
        if self._hidden(t) or (standing == self.hid and not self._last_lost(t)):
            self.hid = standing
            return None
        last_off = self.act["t_off"] if self.act is not None else self.last_off
        crawled = self.act["crawled"] if self.act is not None else self.last_crawled
        # the vehicle the loop saw last if that one left it crawling (or was lost on it), the image showed the loop
        # occupied as it left, and it stood soon after (its track lost as it stopped); else one the tracker never
        # put on the loop (one that drove off at speed is not standing on the loop moments later)
        seen = last_off is not None and crawled and came <= last_off and stood - last_off <= SETTLE_S
        t_on = min(stood, last_off) if seen else stood
        ev = self.tick(t_on)
        self.active[STANDING] = _Presence(t_on, t_on + offset)
        if self.act is None:
            self._start(STANDING, t_on, offset, counted=not seen)
        return ev

    def _hidden(self, t: float) -> bool:
        """Whether the loop's last vehicle crawls or stands just past it on the camera's side: see
        HIDDEN_BEHIND_M."""
        st = self.last_left[1]
        return (not self._last_lost(t) and st[2] < self.y0 and self.y0 - st[2] <= HIDDEN_BEHIND_M
                and st[3] < CRAWL_MPS)

    def _last_lost(self, t: float) -> bool:
        """Whether the loop's last vehicle is no longer tracked."""
        st = self.last_left[1]
        return st is None or t - st[0] > HIDDEN_STALE_S

    def drop(self, vid: int, t: float) -> LoopEvent | None:
        """The vehicle is gone (finished or lost) at t: its presence ends there."""
        if vid in self.active:
            return self._close(vid, t)
        return None

    def tick(self, t: float, sight: LoopSight | None = None) -> LoopEvent | None:
        """Capture time t has come: an actuation whose loop has been free for BRIDGE_S ends, unless the image
        (sight) shows the loop occupied since before it went free: see WAIT_S."""
        act = self.act
        if act is None or self.active or t <= act["t_off"] + BRIDGE_S:
            return None
        if act["crawled"] and sight is not None and sight.came is not None and sight.came <= act["t_off"] \
                and t - act["t_off"] < WAIT_S:
            return None
        return self._emit()

    def _start(self, vid: int, t_on: float, offset: float, counted: bool = True) -> None:
        self.act = {"vid": vid, "t_on": t_on, "wall_on": t_on + offset, "t_off": t_on, "speed": None, "length": None,
                    "counted": counted, "crawled": False}
        if counted:
            self.count += 1
            self.last_on_wall = t_on + offset

    def _close(self, vid: int, t_off: float) -> LoopEvent | None:
        """A vehicle leaves the loop; the actuation ends when no vehicle has been on it for BRIDGE_S."""
        p = self.active.pop(vid)
        if vid != STANDING:  # a standing call's id stands for any vehicle
            self.left.add(vid)
            self.last_left = (vid, None)
        act = self.act
        t_off = max(t_off, p.t_on)
        if t_off >= act["t_off"]:  # the last to leave: did it crawl off (or was it lost crawling)?
            act["crawled"] = not p.speeds or abs(p.speeds[-1]) < CRAWL_MPS
        act["t_off"] = max(act["t_off"], t_off)
        if vid == act["vid"]:
            speed_kmh = float(np.mean(p.speeds)) * 3.6 if p.speeds else None
            other = self.partner
            if other is not None and vid in other.on_times:
                dt = abs(p.t_on - other.on_times[vid])
                if dt > 1e-3:
                    speed_kmh = abs(self.y0 - other.y0) / dt * 3.6
            act["speed"], act["length"] = speed_kmh, p.length
        if not self.active or any(q.t_on <= act["t_off"] + BRIDGE_S for q in self.active.values()):
            return None  # still occupied, or free and waiting for tick
        # the loop went free at act["t_off"]; vehicles that arrived well after it (same frame) start a new one
        ev = self._emit()
        first = min(self.active, key=lambda v: self.active[v].t_on)
        q = self.active[first]
        self._start(first, q.t_on, q.wall_on - q.t_on, counted=first not in self.left)
        return ev

    def _emit(self) -> LoopEvent | None:
        """The actuation in progress is over: its on-interval is kept; its event unless it counted nothing."""
        act, self.act = self.act, None
        self.last_off = act["t_off"]
        self.last_crawled = act["crawled"]
        offset = act["wall_on"] - act["t_on"]
        self.intervals.append((act["wall_on"], act["t_off"] + offset))
        if not act["counted"]:
            return None
        self.last_speed = act["speed"]
        self.last_length = act["length"]
        cls = length_class(act["length"], self.measures)
        if cls is not None:
            self.class_counts[cls] = self.class_counts.get(cls, 0) + 1
        return LoopEvent(
            loop_id=self.cfg.id, channel=self.cfg.channel, lane=self.cfg.lane, t_on=act["t_on"], t_off=act["t_off"],
            wall_on=act["wall_on"], wall_off=act["t_off"] + offset, speed_kmh=act["speed"], length_m=act["length"],
            vehicle_id=act["vid"],
        )

    def occupied_s(self, w0: float, w1: float) -> float:
        """Seconds of [w0, w1] during which the loop was occupied (ongoing presences up to now)."""
        now = self.now_wall if self.now_wall is not None else w1
        ongoing = []
        if self.act is not None:
            act = self.act
            ongoing = [(act["wall_on"], now if self.active else act["t_off"] + act["wall_on"] - act["t_on"])]
        return union_length(self.intervals + ongoing, w0, w1)

    def prune(self, keep_after: float) -> None:
        self.intervals = [iv for iv in self.intervals if iv[1] >= keep_after]
        if len(self.on_times) > 256:
            for vid in list(self.on_times)[:-128]:
                del self.on_times[vid]
        if len(self.left) > 256:
            self.left = set(sorted(self.left)[-128:])  # ids grow with time

    def call(self) -> bool:
        if self.cfg.mode == "pulse":
            return (
                self.last_on_wall is not None
                and self.now_wall is not None
                and self.now_wall - self.last_on_wall < self.cfg.pulse_ms / 1000.0
            )
        return self.act is not None  # held through a dropout shorter than BRIDGE_S

    def channel_state(self, window_s: float, since_wall: float | None) -> ChannelState:
        now = self.now_wall or 0.0
        w0 = now - window_s
        if since_wall is not None:
            w0 = max(w0, since_wall)
        occ = 100.0 * self.occupied_s(w0, now) / (now - w0) if now > w0 else 0.0
        return ChannelState(
            channel=self.cfg.channel, loop_id=self.cfg.id, lane=self.cfg.lane, call=self.call(), count=self.count,
            occupancy_pct=occ, last_speed_kmh=self.last_speed, last_length_m=self.last_length,
            class_counts=dict(self.class_counts),
        )

    def state(self) -> dict:
        return {
            "count": self.count, "class_counts": self.class_counts, "last_speed": self.last_speed,
            "last_length": self.last_length, "intervals": self.intervals,
        }  # an actuation in progress is not kept: after a restart its vehicle is seen anew

    def restore(self, state: dict) -> None:
        self.count = int(state["count"])
        self.class_counts = dict(state["class_counts"])
        self.last_speed, self.last_length = state["last_speed"], state["last_length"]
        self.intervals = [tuple(iv) for iv in state["intervals"]]
