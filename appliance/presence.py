"""Standing vehicles on loops, seen in the image: a loop's patch that differs from the empty road and has
not changed for a while holds the loop's call when the tracker has lost a queued vehicle standing on it."""

from __future__ import annotations

from collections import deque

import cv2
import numpy as np

from appliance.config import SiteConfig
from appliance.types import LoopSight
from appliance.zones import SiteZones

DIFF_GREY = 24  # grey levels (after a 3x3 mean) between a vehicle's pixel and the road under it
OCCUPIED_SHARE = 0.35  # of the patch's pixels: something is on the loop ...
EMPTY_SHARE = 0.12  # ... the loop shows the road again
STILL_LAG_S = 0.5  # the patch now against the patch this long ago ...
STILL_SHARE = 0.04  # ... changed in at most this share of its pixels: nothing on it moves
STAND_S = 1.0  # occupied and still this long: a vehicle stands on the loop
MOVE_OFF_S = 2.0  # a standing vehicle that moves off holds the call this long at most (its rear leaves the loop)
ARRIVE_S = 30.0  # a standing call needs features moving over the loop's stretch of lane this recently ...
ARRIVE_M = 15.0  # ... within this distance of the loop ...
ARRIVE_MPS = 1.0  # ... at least this fast (a patch that changed with nothing coming: a shadow, a parked car)
# A patch learnt as the road after MAX_STAND_S may hold a vehicle standing there (broken down, parked, or at
# the head of a long red's queue): when it leaves, the empty road would read as one standing. Such a road is
# trusted (gives calls) again once the patch matched it within TRUST_S of differing from it with features
# moving over the loop: a vehicle passed and left the road as learnt (as a vehicle moves off, its own patch
# still matches for a moment, hence the difference first). The background a loop starts from is trusted:
# a queue that stands on a loop as the service starts is called, and a vehicle learnt into it (one that
# stood there until the background settled, 10 s in) gives a false call when it leaves, for MAX_STAND_S at most.
TRUST_S = 2.0
# The empty road under a loop is learnt (an approximate median) only while no feature is near: the
# background's median learns a busy lane's traffic, and a standing queue
CLEAR_NEAR_M = 3.0  # ... no feature from this far on the camera's side of the loop ...
CLEAR_FAR_M = 8.0  # ... to this far beyond it (a raised part of a vehicle over the loop is placed there) ...
CLEAR_SIDE_M = 1.0  # ... and this far to its sides (a tall neighbour hides it too)
UPDATE_STEP = 2.0  # grey levels per frame where the patch shows the road it knows ...
RELEARN_STEP = 0.02  # ... and elsewhere
# The background's mean grey below which the road under a loop is lit by every headlight coming, at dusk and
# at night: learnt lit or dark, the empty road reads as a vehicle standing (the synthetic day-to-night scenes
# give false calls from a background mean of 79 down; their days are 100-110, dusk 51-59, night 12-22)
DAYLIGHT_GREY = 85.0
MAX_STAND_S = 240.0  # a standing call or a still patch this long is a change to the road: learnt
SHIFT_KERNEL = np.ones((3, 3), np.uint8)
MARGIN_PX = 1  # the patch's mask is the loop's polygon shrunk by this much (lane markings at its sides)
SHIFT_PX = 16  # the patch keeps this far inside the image, so that the camera's shake and drift keep it in view
LIGHT_STEP_PX = 16  # the frame's light against the background's is measured on this grid


class LoopWatch:
    """One loop's patch of the image against the empty road under it, learnt while no feature is near."""

    def __init__(self, loop_id: str, x_range: tuple[float, float], y_range: tuple[float, float],
                 poly_px: np.ndarray, shape: tuple[int, int]) -> None:
        self.id = loop_id
        self.x_range, self.y_range = x_range, y_range
        h, w = shape
        x0, y0 = np.floor(poly_px.min(axis=0)).astype(int) - 1
        x1, y1 = np.ceil(poly_px.max(axis=0)).astype(int) + 2
        self.box = (max(x0, SHIFT_PX), max(y0, SHIFT_PX), min(x1, w - SHIFT_PX), min(y1, h - SHIFT_PX))
        bx0, by0, bx1, by1 = self.box
        mask = np.zeros((max(by1 - by0, 1), max(bx1 - bx0, 1)), np.uint8)
        cv2.fillPoly(mask, [np.round(poly_px - (bx0, by0)).astype(np.int32)], 1)
        if MARGIN_PX and mask.sum() > 40:  # a loop a few pixels across keeps them all
            mask = cv2.erode(mask, np.ones((2 * MARGIN_PX + 1,) * 2, np.uint8))
        self.mask = mask.astype(bool)
        self.n = max(int(self.mask.sum()), 1)
        self.past: deque[tuple[float, np.ndarray]] = deque()
        self.ref: np.ndarray | None = None
        self.ref_light = 1.0  # the light on the road (LoopPresence.step) when the road was last learnt
        self.trusted = False  # the road learnt gives calls (TRUST_S)
        self.crossed: float | None = None  # when features last moved over the loop, its patch differing
        self.share = 0.0
        self.changed = 1.0
        self.occupied_since: float | None = None
        self.still_since: float | None = None
        self.moving_since: float | None = None
        self.standing: tuple[float, float] | None = None  # the call in progress: when its vehicle came, stood
        self.last_motion: float | None = None

    def forget(self) -> None:
        self.ref, self.trusted = None, False
        self.standing = self.occupied_since = self.still_since = self.moving_since = None
        self.past.clear()

    def _crop(self, img: np.ndarray, offset: tuple[float, float]) -> np.ndarray | None:
        x0, y0, x1, y1 = self.box
        dx, dy = int(round(offset[0])), int(round(offset[1]))
        h, w = img.shape
        if x0 + dx < 0 or y0 + dy < 0 or x1 + dx > w or y1 + dy > h or x1 <= x0 or y1 <= y0:
            return None
        return cv2.blur(img[y0 + dy:y1 + dy, x0 + dx:x1 + dx], (3, 3)).astype(np.float32)

    def _differs(self, a: np.ndarray, b: np.ndarray) -> float:
        """The share of the loop's pixels of a that differ from all of b's within a pixel of them (the camera
        moves by parts of a pixel between frames, and its shift is applied in whole pixels)."""
        lo, hi = cv2.erode(b, SHIFT_KERNEL), cv2.dilate(b, SHIFT_KERNEL)
        off = np.maximum(lo - a, a - hi)[self.mask]
        return np.count_nonzero(off > DIFF_GREY) / self.n

    def step(self, t: float, img: np.ndarray, bg: np.ndarray | None, bg_mean: float, light: float,
             offset: tuple[float, float], moving_here: bool, passing: bool, clear: bool) -> None:
        """bg: the background lined up with img (None until it has settled), bg_mean its mean grey; light: the
        light on the road now, in the background's grey levels (LoopPresence.step); moving_here: features move
        near the loop; passing: features move over it; clear: no feature is near it."""
        if moving_here:
            self.last_motion = t
        p = self._crop(img, offset)
        if p is None:
            self.forget()
            return
        if self.ref is None or self.ref.shape != p.shape:
            road = None if bg is None else self._crop(bg, offset)
            if road is None:
                return
            # the background's median to start with, under the background's own light
            self.ref, self.ref_light, self.trusted = road, bg_mean, True
        road = self.ref * (light / max(self.ref_light, 1.0))  # the light may have changed since
        share = self._differs(p, road)
        # learnt while nothing is near, quickly where the patch shows the road it knows, and slowly elsewhere
        # (a road learnt wrong is put right; a vehicle standing without features is learnt only slowly)
        if clear and self.standing is None:
            step = UPDATE_STEP if share < EMPTY_SHARE else RELEARN_STEP
            self.ref = road + np.clip(p - road, -step, step)
            self.ref_light = light
        if passing and share >= OCCUPIED_SHARE:
            self.crossed = t
        elif share < EMPTY_SHARE and self.crossed is not None and t - self.crossed <= TRUST_S:
            self.trusted = True
        self.share = share
        while len(self.past) >= 2 and t - self.past[1][0] >= STILL_LAG_S:
            self.past.popleft()
        old = self.past[0] if self.past else None
        self.changed = 1.0 if old is None or t - old[0] < STILL_LAG_S else self._differs(p, old[1])
        self.past.append((t, p))

        occupied = self.share >= (EMPTY_SHARE if self.occupied_since is not None else OCCUPIED_SHARE)
        self.occupied_since = _since(self.occupied_since, t, occupied)
        still = occupied and self.changed <= STILL_SHARE
        self.still_since = _since(self.still_since, t, still)
        self.moving_since = _since(self.moving_since, t, occupied and not still)
        since = [x for x in (self.still_since, self.standing and self.standing[1]) if x is not None]
        if since and t - min(since) >= MAX_STAND_S:
            # a change to the road (a parked car, a cone, a road learnt with a vehicle on it): learnt now
            self.standing = self.occupied_since = self.still_since = self.moving_since = None
            self.ref, self.ref_light, self.last_motion, self.trusted = p, light, None, False
        elif self.standing is None:
            if self.trusted and self.still_since is not None and t - self.still_since >= STAND_S \
                    and self.last_motion is not None and t - self.last_motion <= ARRIVE_S:
                # still since: the patch matched itself STILL_LAG_S before that
                self.standing = (self.occupied_since, max(self.occupied_since, self.still_since - STILL_LAG_S))
        elif not occupied or (self.moving_since is not None and t - self.moving_since >= MOVE_OFF_S):
            self.standing = None


def _since(since: float | None, t: float, on: bool) -> float | None:
    """When a condition that holds at t (on) began: since, or t if it did not hold before."""
    if not on:
        return None
    return t if since is None else since


class LoopPresence:
    """All loops' watches; ``sights`` holds what the image shows on each loop (an empty LoopSight while the
    image is not asked: below DAYLIGHT_GREY, or before the background is ready)."""

    def __init__(self, site: SiteConfig, zones: SiteZones) -> None:
        H = zones.H
        self.watches: list[LoopWatch] = []
        self.clear: list[tuple[float, float]] = []  # along-road window per loop that must hold no feature
        shape = (zones.height, zones.width)
        for lp in site.loops:
            poly = np.asarray(lp.polygon_m, dtype=np.float64)
            x0, y0 = poly.min(axis=0)
            x1, y1 = poly.max(axis=0)
            px = H.road_to_img(poly)
            self.watches.append(LoopWatch(lp.id, (float(x0), float(x1)), (float(y0), float(y1)), px, shape))
            xm = 0.5 * (x0 + x1)
            rows = H.road_to_img(np.array([[xm, y0], [xm, y1]]))[:, 1]
            away = 1.0 if rows[1] < rows[0] else -1.0  # the direction along the road away from the camera
            near, far = (CLEAR_NEAR_M, CLEAR_FAR_M) if away > 0 else (CLEAR_FAR_M, CLEAR_NEAR_M)
            self.clear.append((float(y0) - near, float(y1) + far))
        self.sights: dict[str, LoopSight] = {w.id: LoopSight() for w in self.watches}

    def keep(self, old: LoopPresence) -> None:
        """Take over old's watches of the loops that have not changed (same id, same patch)."""
        was = {w.id: (w, c) for w, c in zip(old.watches, old.clear)}
        for i, w in enumerate(self.watches):
            prev = was.get(w.id)
            if prev is not None and prev[0].box == w.box and np.array_equal(prev[0].mask, w.mask) \
                    and prev[1] == self.clear[i]:
                self.watches[i] = prev[0]
                self.sights[w.id] = old.sights[w.id]

    def step(self, t: float, img: np.ndarray, bg: np.ndarray | None, offset: tuple[float, float],
             feat_s: np.ndarray) -> None:
        """bg: the background lined up with img (None until it has settled: appliance.background); feat_s: the
        live features' road states (x, y, vx, vy).
        Below DAYLIGHT_GREY the image is not asked, and what was learnt is forgotten."""
        if not self.watches:
            return
        bg_sub = None if bg is None else bg[::LIGHT_STEP_PX, ::LIGHT_STEP_PX].astype(np.float32)
        bg_mean = 0.0 if bg_sub is None else float(bg_sub.mean())
        if bg_mean < DAYLIGHT_GREY:
            for w in self.watches:
                w.forget()
                self.sights[w.id] = LoopSight()
            return
        # the light now: the background follows a cloud's shadow only over tens of seconds; the median ratio of
        # the frame to it is the road's, vehicles covering less than half of the image
        lit = bg_sub > 16.0
        ratio = img[::LIGHT_STEP_PX, ::LIGHT_STEP_PX][lit] / bg_sub[lit]
        light = bg_mean * (float(np.median(ratio)) if ratio.size else 1.0)
        x, y, vy = feat_s[:, 0], feat_s[:, 1], np.abs(feat_s[:, 3])
        for w, (c0, c1) in zip(self.watches, self.clear):
            lo, hi = w.y_range
            moving_in_lane = (x >= w.x_range[0]) & (x <= w.x_range[1]) & (vy >= ARRIVE_MPS)
            moving = moving_in_lane & (y >= lo - ARRIVE_M) & (y <= hi + ARRIVE_M)
            passing = moving_in_lane & (y >= lo) & (y <= hi)
            near = (x >= w.x_range[0] - CLEAR_SIDE_M) & (x <= w.x_range[1] + CLEAR_SIDE_M) & (y >= c0) & (y <= c1)
            w.step(t, img, bg, bg_mean, light, offset, bool(moving.any()), bool(passing.any()), not near.any())
            self.sights[w.id] = LoopSight(w.occupied_since, w.standing)
