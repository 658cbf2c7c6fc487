"""The vision pipeline: repeated-frame check, stabilisation, corner detection, tracking, grouping.

One ``step`` per frame returns the vehicles in view (provisional) and those finalised this frame; a new
vehicle's first report is held back HOLD_S and carries its trajectory back to its lane's region entry.
"""

from __future__ import annotations

import time
from dataclasses import replace
from functools import partial

import cv2
import numpy as np

from appliance.background import Background
from appliance.config import SiteConfig, at_working_size
from appliance.corners import CornerDetector, dim_scale
from appliance.edie import back_to_entry
from appliance.grouping import RECHECK_S, SETTLED_AGE, STILL_M, STILL_S, Grouper
from appliance.presence import LoopPresence
from appliance.stabilise import Stabiliser
from appliance.tracker import FeatureTracker
from appliance.types import Frame, LoopSight, VehicleState
from appliance.zones import LANE_MARGIN_M, SiteZones

REPEAT_GRID = 4  # subsampling step of the repeated-frame check
# A frame repeats the previous one when no grid pixel changed by more than this: encoder duplicates
# differ by coding noise only (<= 15 grey levels in H.264 at crf 23), anything moving changes far more.
# A genuinely still frame is skipped too, which loses nothing.
REPEAT_MAX_DIFF = 20
NIGHT_GREY = 40.0  # a frame darker than this on average is a night scene (day scenes: 90-140, night: 10-25)
LK_WIN = (15, 15)
LK_LEVELS = 3
LK_MARGIN_PX = 64  # crop margin around new corners for the initial-velocity flow (> motion per frame)
# A vehicle hidden behind one of the other direction while it crossed its detection zone is first seen where
# that one uncovers it: corners are also looked for where a reported vehicle of the next lane, of the other
# direction, covered a lane in the last REVEAL_S and none covers now (kept on a grid of REVEAL_CELL_PX cells;
# the current covers grown by REVEAL_GROW cells, and up and sideways by their size: a body reaches beyond its
# features). Behind one of its own direction, what is uncovered is mostly the occluder's own body and its top
# seen over the next lane (new groups there were counted as vehicles by the dozen: +18 to +53 % on the trucks,
# dense and shockwave scenes); two lanes away, mostly the tops of the lane between's vehicles (counted there).
REVEAL_S = 1.0
REVEAL_CELL_PX = 4
REVEAL_GROW = 1
REVEAL_MIN_MPS = 1.5  # ... and kept only where they move their lane's way this fast (grouping.MIN_SPEED_MPS)
# Started (or restarted) in traffic, the vehicles already past their detection zones are looked for as well, for
# STARTUP_S from the first frame: corners anywhere in a lane short of its count line, kept as revealed ones are.
# (Not past it: found all at once, a platoon's vehicles at one speed are grouped as one, and one already past
# the line would take the count of the one behind it.)
STARTUP_S = 0.2
STALE_GAP_S = 0.5  # a leading trajectory point this much older than the next one ...
STALE_SPEED_SHARE = 0.5  # ... and reached at less than this share of the vehicle's speed is dropped
STALL_SHARE = 0.7  # held points covered at less than this share of the near end's speed stood still a while
BACKFILL_MIN_SPEED = 1.0  # m/s: slower vehicles are not extrapolated back to the region entry
# A new vehicle's points up to a standstill (within STILL_M for STILL_S) are not its own when it could not
# have got from standing there to where it is now at up to MAX_ACCEL_MPS2, plus START_SLACK_MPS (the
# standstill's tolerance lets it end with the vehicle already creeping off): the group began on something
# static (an occluder's edge where vehicles emerge) that the vehicle's own features joined as it passed.
MAX_ACCEL_MPS2 = 5.0
START_SLACK_MPS = 3.0
OWN_MAX_POINTS = 750  # only a new vehicle's last points are searched for a standstill (n x n comparison)
BACKFILL_MIN_FEATURES = 4  # groups with fewer features when released are not extended (fragments)
# A newly reported vehicle is held back this long (capture seconds) before its first report goes out, so
# its speed is measured over its own points before its trajectory is extended back to the region entry,
# and a group that merges into another meanwhile never reaches the measures.
HOLD_S = 0.5
# ... longer while it is matching a vehicle it may be a part of (grouping's recheck votes), up to RECHECK_S:
# released before the votes are in, a part crossing the count line would already be a count
HOLD_MIN_TRAVEL_M = 3.0  # ... and until it has moved this far (an occluder's edge where vehicles emerge does not)
# A feature that loses this much speed faster than a vehicle can brake has latched onto something static
# (an occluder's edge where vehicles pass behind it): it is dropped.
STOP_LOSS_MPS = 8.0
MAX_BRAKE_MPS2 = 12.0
ALIGN_MIN_PX = 0.5  # camera shifts between frames below this leave the previous frame as it is (resampling
# it would only blur it; a still camera's stabiliser jitters by a few hundredths of a pixel)


def top_field(img: np.ndarray) -> np.ndarray:
    """An interlaced frame's top field (its even lines, all taken at the frame's time) at full height: each
    odd line the mean of the field lines above and below it (the last line, with none below, a copy)."""
    out = np.empty_like(img)
    f = img[0::2]
    k = len(f) - 1  # odd lines with a field line on both sides
    out[0::2] = f
    out[1:2 * k:2] = cv2.addWeighted(f[:k], 0.5, f[1:], 0.5, 0.0)
    if img.shape[0] % 2 == 0:
        out[-1] = f[-1]
    return out


class VisionPipeline:
    """Stages in order; each holds its own state. ``stats`` has live numbers, ``timings`` seconds per stage."""

    def __init__(self, site: SiteConfig) -> None:
        self.site = site
        self.width, self.height = int(site.source.width), int(site.source.height)
        self.deinterlace = bool(site.source.deinterlace)
        work = at_working_size(site)  # the stages work in its pixels
        self.work_size = (int(work.source.width), int(work.source.height))
        self._up = np.array([self.width / self.work_size[0], self.height / self.work_size[1]])  # to the camera's
        self.zones = SiteZones(work)
        H = work.homography
        p = site.tracking
        self.p = p
        self.stabiliser = Stabiliser(work.fiducials, self.zones.lane_image, enabled=p.stabilise)
        self.detector = CornerDetector(p, self.zones.detection_roi, self.zones.detection_mask_roi)
        self.tracker = FeatureTracker(p, H.H, H.Hinv)
        self.grouper = Grouper(p, self.zones)
        self.background = Background()
        self.presence = LoopPresence(work, self.zones) if p.standing_calls else None
        self.prev: np.ndarray | None = None
        self.prev_grid: np.ndarray | None = None
        self.prev_t: float | None = None
        self.first_t: float | None = None  # capture time of the first frame (backfill never goes before it)
        self.held: dict[int, list[VehicleState]] = {}  # vehicle id -> its states since its first report
        self.offset = (0.0, 0.0)
        self.prev_offset = (0.0, 0.0)  # the stabiliser's offset at self.prev
        # (lane, neighbouring lane of the other direction whose vehicles may hide one of it), see REVEAL_S
        z = self.zones
        n = len(z.lanes)
        self.reveal_pairs = [(j, i) for j in range(n) for i in (j - 1, j + 1)
                             if 0 <= i < n and z.lanes[i].sign != z.lanes[j].sign]
        cells = (-(-z.height // REVEAL_CELL_PX), -(-z.width // REVEAL_CELL_PX)) if self.reveal_pairs else (0, 0)
        # per lane and grid cell (zone coordinates), when a reported vehicle of that lane last covered it
        self.covered_t = np.full((n, *cells), -np.inf, np.float32)
        self.covers = np.zeros((0, 4), np.int32)  # the cells reported vehicles cover now (x0, y0, x1, y1)
        # the cells of each lane where a vehicle may be revealed: past its detection zone, short of its exit zone
        beyond = (z.detection_image == 0) & (z.exit_image == 0)
        self.reveal_cells = np.stack([
            cv2.resize(((z.lane_image == lz.index) & beyond).astype(np.uint8) * 255, cells[::-1],
                       interpolation=cv2.INTER_AREA) > 0 if self.reveal_pairs else np.zeros(cells, np.bool_)
            for lz in z.lanes])
        rows, cols = np.mgrid[0:z.height, 0:z.width]
        with np.errstate(divide="ignore", invalid="ignore"):  # the horizon's row, outside every lane
            road_y = z.H.img_to_road(np.column_stack([cols.ravel(), rows.ravel()]))[:, 1].reshape(z.height, z.width)
        short = np.zeros((z.height, z.width), np.bool_)  # each lane short of its count line
        for lz in z.lanes:
            short |= (z.lane_image == lz.index) & ((road_y - lz.count_y) * lz.sign < 0.0)
        self.startup_zone = _zone_of(short & beyond)
        self.last_states: list[VehicleState] = []
        self.stats: dict = {
            "frames": 0, "features": 0, "vehicles": 0, "finished": 0, "shake_px": (0.0, 0.0),
            "fiducials_ok": 0, "fiducials_total": 0, "repeated_frames": 0, "mean_grey": 0.0,
        }
        self.timings: dict[str, float] = {"stabilise": 0.0, "track": 0.0, "detect": 0.0, "group": 0.0, "presence": 0.0}

    # ------------------------------------------------------------------------------------------
    def warmup(self) -> None:
        """Compile (or load from cache) every numba kernel on dummy data, leaving no state behind."""
        from appliance.background import shadow_at, temporal_median
        from appliance.corners import select_spaced
        from appliance.grouping import (alone_groups, assign_ids, components, fit_places, fitted_places,
                                        group_medians, group_summary, isolate, pair_update, unbridge)
        from appliance.tracker import init_features, track_step

        p = self.p
        T = p.template_px
        img = (np.arange(64 * 64).reshape(64, 64) * 37 % 251).astype(np.uint8)
        n = 4
        alive = np.ones(n, np.bool_)
        px = np.full((n, 2), 32.0)
        s = np.zeros((n, 4))
        s[:, :2] = 32.0
        P = np.tile(np.eye(4), (n, 1, 1))
        tmpl = np.zeros((n, T, T), np.float32)
        ok = np.zeros(n, np.bool_)
        init_features(img, np.arange(n, dtype=np.int64), px, tmpl, ok)
        eye = np.eye(3)
        track_step(img, eye, eye, 0.0, 0.0, 0.04, alive, px, s, P, tmpl, np.zeros(n, np.int32),
                   np.zeros(n, np.int32), np.zeros(n, np.float32), 2, 0.7, 3.0, 0.5, 8.0, 4.0, 50.0, 2, 0.9)
        select_spaced(np.zeros((3, 2)), np.zeros((1, 2)), 4.0, 2, np.zeros(2, np.int64))
        live = np.arange(n, dtype=np.int64)
        state = np.zeros((n, n), np.int8)
        pair_update(live, s, np.ones(n, np.int32), np.zeros(n, np.int8), state, np.zeros((n, n, 4), np.float32),
                    np.zeros((n, n), np.float32), 2.5, 5.0, 1.0, 2.0, 0.1, np.zeros(n, np.bool_))
        components(live, state, np.zeros(n, np.int64))
        owner = np.array([-1, 1, 2, -1], np.int64)
        kept = unbridge(live[:1], live, owner, s, state)
        isolate(live[:1], kept, live, owner, state)
        labels, vids = np.zeros(n, np.int64), np.full(n, -1, np.int64)
        assign_ids(live, labels, vids, 1, np.zeros(0, np.int64))
        fit_places(live, np.full(n, 3, np.int32), s, np.zeros((n, 5)), vids, 1, 10.0, 0.0, 1.5, 10, 2.25, 1.0)
        fitted_places(live, np.zeros((n, 5)), vids, 1, 1.5, 10, 2.25)
        group_summary(live, s, px, np.full(n, 3, np.int32), 3.0, 1.0, 4.0, 1.0, 1.08, 10.0)
        group_medians(live, np.array([0, n], np.int64), s, np.zeros(n, np.int32))
        alone_groups(np.ones(1, np.int64), np.zeros(1), np.zeros(1), np.ones(1), np.zeros((1, 8)), 0.0, 0.0, 1.5)
        shadow_at(img, img, np.array([[8.0, 8.0], [16.0, 16.0]]), True)
        temporal_median(np.stack([img, img, img]), np.empty_like(img))

    # ------------------------------------------------------------------------------------------
    def _check_frame(self, frame: Frame) -> np.ndarray:
        img = frame.image
        if not isinstance(img, np.ndarray) or img.ndim not in (2, 3):
            raise ValueError(f"frame {frame.seq}: image must be a 2-D grey (or 3-D BGR) array")
        if img.ndim == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        if img.shape != (self.height, self.width):
            raise ValueError(
                f"frame {frame.seq}: size {img.shape[1]}x{img.shape[0]} does not match the config's "
                f"source.width x source.height = {self.width}x{self.height}"
            )
        if img.dtype != np.uint8:
            raise ValueError(f"frame {frame.seq}: image dtype {img.dtype}, expected uint8")
        img = top_field(img) if self.deinterlace else np.ascontiguousarray(img)
        if self.work_size != (self.width, self.height):
            img = cv2.resize(img, self.work_size, interpolation=cv2.INTER_AREA)
        return img

    def step(self, frame: Frame) -> list[VehicleState]:
        img = self._check_frame(frame)
        st = self.stats
        st["frames"] += 1
        grid = img[::REPEAT_GRID, ::REPEAT_GRID]
        st["mean_grey"] = float(grid.mean())
        self.grouper.lights_only = st["mean_grey"] < NIGHT_GREY
        self.detector.scale = 1.0 if self.grouper.lights_only else dim_scale(st["mean_grey"])
        if self.prev_grid is not None:
            _, peak, _, _ = cv2.minMaxLoc(cv2.absdiff(grid, self.prev_grid))
            repeated = frame.repeated or peak <= REPEAT_MAX_DIFF
            if repeated or (self.prev_t is not None and frame.t <= self.prev_t):
                st["repeated_frames"] += 1
                # the same vehicles again, without the trajectories that went out with them already
                return [replace(v, trajectory=None) for v in self.last_states if not v.finished]
        self.prev_grid = grid.copy()
        dt = 0.0 if self.prev_t is None else frame.t - self.prev_t
        self.prev_t = frame.t
        if self.first_t is None:
            self.first_t = frame.t
        tm = self.timings

        c0 = time.perf_counter()
        self.prev_offset = self.offset
        self.offset = self.stabiliser.step(img)
        c1 = time.perf_counter()
        tr = self.tracker
        if dt > 0:
            tr.step(img, self.offset, dt)
            self._drop_features(frame.t)
        c2 = time.perf_counter()
        if self.prev is not None and dt > 0:
            self._detect(img, dt, frame.t)
        c3 = time.perf_counter()
        self.background.update(img, self.offset)
        states, retire = self.grouper.step(frame.t, tr.s, tr.px, tr.lane, tr.alive, tr.age,
                                           lambda pts, caster: self._is_shadow(img, pts, caster),
                                           partial(self.background.is_joined, img))
        if len(retire):
            tr.kill(retire)
        self._note_covers(frame.t)
        states = self._hold_new(states)
        c4 = time.perf_counter()
        bg = self.background
        if self.presence is not None:
            self.presence.step(frame.t, img, bg.aligned if bg.settled else None, self.offset, tr.s[tr.live()])
        c5 = time.perf_counter()
        tm["stabilise"] += c1 - c0
        tm["track"] += c2 - c1
        tm["detect"] += c3 - c2
        tm["group"] += c4 - c3
        tm["presence"] += c5 - c4

        self.prev = img
        self.last_states = states
        st["features"] = int(tr.alive.sum())
        st["vehicles"] = sum(1 for v in states if not v.finished)
        st["finished"] = self.grouper.finished_total
        st["shake_px"] = (round(self.offset[0] * self._up[0], 2), round(self.offset[1] * self._up[1], 2))
        st["fiducials_ok"] = self.stabiliser.n_ok
        st["fiducials_total"] = self.stabiliser.n_total
        return states

    def watch_loops(self, site: SiteConfig) -> None:
        """The site's loops changed (a config reload that kept the pipeline): watch the new and moved loops'
        patches afresh; a loop left as it was keeps what its watch has learnt (a road learnt afresh from the
        background may hold a vehicle standing there now: see appliance.presence.TRUST_S)."""
        old = self.presence
        self.site = site
        self.presence = LoopPresence(at_working_size(site), self.zones) if self.p.standing_calls else None
        if old is not None and self.presence is not None:
            self.presence.keep(old)

    @property
    def loop_sights(self) -> dict[str, LoopSight]:
        """What the image shows on each loop (appliance.presence), if asked (tracking.standing_calls)."""
        return self.presence.sights if self.presence is not None else {}

    def _is_shadow(self, img: np.ndarray, pts: np.ndarray, caster: np.ndarray | None) -> bool:
        """The grouper's image test: are pts only a shadow on the road (that reaches the caster's points)? With
        no caster to show for it, the road's texture must be seen through the shadow."""
        if caster is None:
            return self.background.is_shadow(img, pts, plain_ok=False)
        return self.background.is_attached_shadow(img, pts, caster)

    def _hold_new(self, states: list[VehicleState]) -> list[VehicleState]:
        """Hold each new vehicle's states for HOLD_S, then release them as one report whose trajectory
        runs from the region entry (backfilled) through the held points."""
        out = []
        seen = set()
        for v in states:
            held = self.held.get(v.id)
            if v.joined is not None and held is not None:
                continue  # a part of another vehicle: never a vehicle of its own (dropped below)
            if held is None and v.trajectory is None:
                out.append(v)
                continue
            if held is None:
                held = self.held[v.id] = []
            held.append(v)
            seen.add(v.id)
            moved = abs(v.y_front - held[0].y_front) >= HOLD_MIN_TRAVEL_M
            waited = v.t - held[0].t
            if v.finished or (waited >= HOLD_S and moved and not (
                    waited < RECHECK_S and self.grouper.matching_host(v.id))):
                del self.held[v.id]
                first = _released(held)  # v itself, with the held points before it
                if not v.finished or v.t - held[0].t >= 0.5 * HOLD_S:
                    self._backfill(first, held)
                else:  # gone right after its report: no speed to extend it back with (a crawl would be minutes)
                    self._own_points(first, held)
                out.append(first)
        for vid in [vid for vid in self.held if vid not in seen]:
            # gone (merged into another vehicle, or lost) while held: if it moved, its points go out as
            # observed, without a backfill, so that a line it crossed meanwhile still counts; a group that
            # never moved (features stuck on an occluder's edge where vehicles emerge) is dropped
            held = self.held.pop(vid)
            if vid in self.grouper.merged_now:
                continue  # a part of another vehicle: never a vehicle of its own
            if abs(held[-1].y_front - held[0].y_front) < HOLD_MIN_TRAVEL_M:
                continue
            gone = _released(held)
            self._own_points(gone, held)
            out.append(gone)
        return out

    def _group_speed(self, vid: int) -> float:
        """Median along-road speed of a vehicle's settled, moving features (0 when it has none). Right
        after a vehicle's first report its own velocity may still lean on a feature that is not moving
        (an occluder's edge where it emerged)."""
        tr = self.tracker
        live = tr.live()
        m = live[self.grouper.fvid[live] == vid]
        vy = np.abs(tr.s[m, 3])
        ok = (vy > BACKFILL_MIN_SPEED) & (tr.age[m] >= 3)
        return float(np.median(vy[ok])) if ok.any() else 0.0

    def _own_points(self, v: VehicleState, held: list[VehicleState] | None) -> tuple[list, float, float]:
        """Drop a newly reported vehicle's leading trajectory points that were not its own: those up to a
        standstill it could not have moved off from (see _own_start), and a first point it could not have
        come from at anything like its speed. Both were something static it passed, which its group began
        on. Returns its points left (the last one its state), its along-road velocity and its speed."""
        pts = list(v.trajectory or []) + [(v.t, v.x, v.y_front)]
        own = _own_start(np.array([p[0] for p in pts]), np.array([p[2] for p in pts]))
        pts = pts[own:]
        vy = v.vy
        if own:  # its velocity still leans on the standing features: its own speed is over what it did since
            vy = (pts[-1][2] - pts[0][2]) / (pts[-1][0] - pts[0][0])
            speed = abs(vy)
        elif held and held[-1].t - held[0].t >= 0.5 * HOLD_S:
            # measured over the held points (elevated features' speeds are magnified), unless far below the
            # near end's own: its points may have stood still a while when its lowest feature was lost. The
            # median of its steps: a near end that starts behind its front jumps when a lower feature appears
            rate = _median_step_rate(held)
            speed = rate if rate >= STALL_SHARE * abs(v.vy) else abs(v.vy)
        else:
            speed = max(abs(v.vy), self._group_speed(v.id))
        # a group's first point may come from a static feature it was chained to before the vehicle
        # arrived: drop leading points from which the vehicle could not have come at anything like its speed
        while len(pts) >= 2 and pts[1][0] - pts[0][0] > STALE_GAP_S \
                and abs(pts[1][2] - pts[0][2]) < STALE_SPEED_SHARE * speed * (pts[1][0] - pts[0][0]):
            pts.pop(0)
        v.trajectory = pts[:-1] or None
        return pts, vy, speed

    def _backfill(self, v: VehicleState, held: list[VehicleState] | None = None) -> None:
        """Extend a newly reported vehicle's own trajectory (see _own_points) back to where it entered its
        lane's Edie region.

        Far away (small in the image) a vehicle is tracked only once it is big enough to hold features,
        so its first points lie inside the region; it crossed the region's entry earlier. Assuming the
        speed it has now over that stretch, the entry point is prepended (never before the first frame),
        so Edie's d(A) and t(A) cover the whole region."""
        pts, vy, speed = self._own_points(v, held)
        traj = pts[:-1]
        t0, x0, y0 = pts[0]
        lz = self.zones.lane_at_road(v.x, v.y_front) or self.zones.lane_at_road(x0, y0)
        if v.n_features < BACKFILL_MIN_FEATURES:
            return  # a few features only: likely a fragment of another vehicle, not extended
        if lz is None or vy * lz.sign < BACKFILL_MIN_SPEED or speed < BACKFILL_MIN_SPEED or self.first_t is None:
            return
        if (y0 - lz.count_y) * lz.sign > 0.0:
            return  # first seen past the count line: the backfill must not make a count
        entry = back_to_entry(t0, y0, lz.region_y[1] if lz.sign < 0 else lz.region_y[0], lz.sign, speed,
                              self.first_t)
        if entry is None:
            return
        v.trajectory = [(entry[0], x0, entry[1])] + list(traj)
        v.backfilled = True
        self.stats["backfilled"] = self.stats.get("backfilled", 0) + 1

    def _drop_features(self, t: float) -> None:
        tr = self.tracker
        live = tr.live()
        if not len(live):
            return
        ext = self.zones.lane_extent_by_index[tr.lane[live]]
        y = tr.s[live, 1]
        outside = (y < ext[:, 0] - LANE_MARGIN_M) | (y > ext[:, 1] + LANE_MARGIN_M)
        static = (t - tr.born_t[live] > self.p.static_drop_s) & (tr.max_disp[live] < self.p.static_min_move_px)
        # a feature moving against its lane's direction is on something else (shadow edge, noise)
        sign = self.zones.sign_by_index[tr.lane[live]]
        wrong = (tr.age[live] >= 3) & (tr.s[live, 3] * sign < -1.0)
        v = np.abs(tr.s[live, 3])
        settled = tr.age[live] >= SETTLED_AGE
        up = settled & (v >= tr.vmax[live])
        tr.vmax[live[up]] = v[up]
        tr.t_vmax[live[up]] = t
        lost = tr.vmax[live] - v
        halted = settled & (lost > STOP_LOSS_MPS) & (lost > MAX_BRAKE_MPS2 * (t - tr.t_vmax[live]))
        drop = live[outside | static | wrong | halted]
        if len(drop):
            tr.kill(drop)

    def _aligned_prev(self) -> np.ndarray:
        """The previous frame moved by the camera's shift since then, so that static scenery lines up with the
        current frame: the motion mask then sees vehicles only (not every edge the shake moved) and the new
        corners' initial velocities carry no camera motion."""
        d = (self.offset[0] - self.prev_offset[0], self.offset[1] - self.prev_offset[1])
        if abs(d[0]) < ALIGN_MIN_PX and abs(d[1]) < ALIGN_MIN_PX:
            return self.prev
        M = np.float32([[1, 0, d[0]], [0, 1, d[1]]])
        return cv2.warpAffine(self.prev, M, (self.width, self.height), flags=cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_REPLICATE)

    def _detect(self, img: np.ndarray, dt: float, t: float) -> None:
        tr = self.tracker
        live = tr.live()
        free = tr.capacity - len(live)
        if free <= 0:
            return
        shift = (int(round(self.offset[0])), int(round(self.offset[1])))
        prev = self._aligned_prev()
        # corners in the lanes keep their spacing from the lanes' features only: a top seen off the lane, right
        # at its edge, must not keep the vehicle's own corners there from being found
        pts = self.detector.detect(img, prev, tr.px[live[~self.grouper.lifted[live]]], shift)[:free]
        revealed = np.zeros(len(pts), np.bool_)
        reveal = self.startup_zone if t - self.first_t <= STARTUP_S else self._revealed(t)
        if reveal is not None and len(pts) < free:
            more = self.detector.detect(img, prev, np.concatenate([tr.px[live], pts]), shift, reveal)[:free - len(pts)]
            pts = np.concatenate([pts, more])
            revealed = np.r_[revealed, np.ones(len(more), np.bool_)]
        lifted = self.zones.lifted_zone
        if lifted is not None and len(pts) < free:  # vehicles' tops off the lanes: what the lanes leave over
            more = self.detector.detect(img, prev, np.concatenate([tr.px[live], pts]), shift, lifted)[:free - len(pts)]
            pts = np.concatenate([pts, more])
            revealed = np.r_[revealed, np.zeros(len(more), np.bool_)]
        if not len(pts):
            return
        # where each new corner was one frame earlier (pyramidal LK), for its initial velocity
        # (on a crop around the new corners: pyramids of the whole frame would cost more than the rest)
        m = LK_MARGIN_PX
        h, w = img.shape
        x0, y0 = max(0, int(pts[:, 0].min()) - m), max(0, int(pts[:, 1].min()) - m)
        x1, y1 = min(w, int(pts[:, 0].max()) + m + 1), min(h, int(pts[:, 1].max()) + m + 1)
        p0 = (pts - [x0, y0]).astype(np.float32).reshape(-1, 1, 2)
        prev_pts, status, _ = cv2.calcOpticalFlowPyrLK(
            img[y0:y1, x0:x1], prev[y0:y1, x0:x1], p0, None, winSize=LK_WIN, maxLevel=LK_LEVELS)
        ok = status.reshape(-1).astype(bool)
        pts, prev_pts = pts[ok], prev_pts.reshape(-1, 2)[ok].astype(np.float64) + [x0, y0]
        ref = pts - np.asarray(self.offset)
        lanes = self.zones.lane_at_px(ref, lifted=True)
        keep = lanes > 0
        revealed = revealed[ok] & keep
        if revealed.any():
            # a vehicle revealed moves its lane's way: not the road it uncovered, nor the occluder's own parts
            H = self.zones.H
            dy = H.img_to_road(ref[revealed])[:, 1] - H.img_to_road(prev_pts[revealed] - self.offset)[:, 1]
            keep[revealed] = dy * self.zones.sign_by_index[lanes[revealed]] >= REVEAL_MIN_MPS * dt
        pts, prev_pts, lanes = pts[keep], prev_pts[keep], lanes[keep]
        if not len(pts):
            return
        slots = tr.add(img, pts, prev_pts, self.offset, dt, t, lanes)
        self.grouper.reset_slots(slots, self.zones.lane_at_px(tr.born_px[slots]) == 0)

    def _note_covers(self, t: float) -> None:
        """Mark the cells each reported vehicle's features span now as covered at t by its lane (see REVEAL_S)."""
        if not self.reveal_pairs:
            return
        tr = self.tracker
        live = tr.live()
        vids = self.grouper.fvid[live]
        tracks = self.grouper.tracks
        reported = np.array([vid for vid, g in tracks.items() if g.reported and g.lane_index > 0], np.int64)
        on = np.isin(vids, reported)
        if on.sum() < 2:
            self.covers = np.zeros((0, 4), np.int32)
            return
        v = vids[on]
        p = (tr.px[live[on]] - np.asarray(self.offset)) / REVEAL_CELL_PX
        order = np.argsort(v, kind="stable")
        v, p = v[order], p[order]
        starts = np.flatnonzero(np.r_[True, v[1:] != v[:-1]])
        lo = np.column_stack([np.minimum.reduceat(p[:, 0], starts), np.minimum.reduceat(p[:, 1], starts)])
        hi = np.column_stack([np.maximum.reduceat(p[:, 0], starts), np.maximum.reduceat(p[:, 1], starts)])
        self.covers = np.floor(np.concatenate([lo, hi], axis=1)).astype(np.int32)
        for (x0, y0, x1, y1), vid in zip(self.covers, v[starts]):
            self.covered_t[tracks[int(vid)].lane_index - 1, max(y0, 0):max(y1 + 1, 0), max(x0, 0):max(x1 + 1, 0)] = t

    def _revealed(self, t: float) -> tuple[tuple[int, int, int, int], np.ndarray] | None:
        """The lanes' cells (past their detection zones, short of their exit zones) a reported vehicle of a next
        lane of the other direction covered in the last REVEAL_S and no vehicle covers now, as a detector zone
        (ROI, mask) in zone coordinates; None if none."""
        if not self.reveal_pairs:
            return None
        cells = np.zeros(self.covered_t.shape[1:], np.bool_)
        for j, i in self.reveal_pairs:
            cells |= (self.covered_t[i] >= t - REVEAL_S) & self.reveal_cells[j]
        g = REVEAL_GROW
        for x0, y0, x1, y1 in self.covers:
            # a vehicle's body reaches above and beside its features (its roof seen over the next lane)
            w, h = (x1 - x0) // 2 + g, y1 - y0 + g
            cells[max(y0 - h, 0):max(y1 + g + 1, 0), max(x0 - w, 0):max(x1 + w + 1, 0)] = False
        box = _bounds(cells)
        if box is None:
            return None
        c0, r0, c1, r1 = box
        mask = cv2.resize(cells[r0:r1, c0:c1].astype(np.uint8) * 255, None, fx=REVEAL_CELL_PX, fy=REVEAL_CELL_PX,
                          interpolation=cv2.INTER_NEAREST)
        x0, y0 = c0 * REVEAL_CELL_PX, r0 * REVEAL_CELL_PX
        x1, y1 = min(x0 + mask.shape[1], self.zones.width), min(y0 + mask.shape[0], self.zones.height)
        return (x0, y0, x1, y1), np.ascontiguousarray(mask[:y1 - y0, :x1 - x0])

    # ------------------------------------------------------------------------------------------
    def overlay(self, image: np.ndarray) -> np.ndarray:
        """BGR drawing of lanes, zones, features and vehicles (one colour per vehicle) with ids, on the camera's
        frame."""
        out = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image.copy()

        def up(pts: np.ndarray) -> np.ndarray:  # working pixels to the camera's
            return np.round(np.asarray(pts, np.float64) * self._up).astype(np.int32)

        for lz in self.zones.lanes:
            cv2.polylines(out, [up(lz.polygon_px)], True, (200, 200, 200), 1, cv2.LINE_AA)
            if len(lz.detection_px) >= 3:
                cv2.polylines(out, [up(lz.detection_px)], True, (0, 200, 0), 1)
            if len(lz.exit_px) >= 3:
                cv2.polylines(out, [up(lz.exit_px)], True, (0, 0, 220), 1)
            c = up(self.zones.H.road_to_img(
                [[lz.polygon_m[:, 0].min(), lz.count_y], [lz.polygon_m[:, 0].max(), lz.count_y]]))
            cv2.line(out, tuple(map(int, c[0])), tuple(map(int, c[1])), (0, 220, 220), 1)
        tr, g = self.tracker, self.grouper
        live = tr.live()
        for i, (x, y) in zip(live, up(tr.px[live])):
            vid = int(g.fvid[i])
            col = _colour(vid) if vid in g.tracks and g.tracks[vid].reported else (128, 128, 128)
            cv2.circle(out, (int(x), int(y)), 2, col, -1)
        for vid, trk in g.tracks.items():
            if not trk.reported:
                continue
            members = live[g.fvid[live] == vid]
            if not len(members):
                continue
            pts = up(tr.px[members])
            x0, y0 = pts.min(axis=0)
            x1, y1 = pts.max(axis=0)
            col = _colour(vid)
            cv2.rectangle(out, (int(x0) - 3, int(y0) - 3), (int(x1) + 3, int(y1) + 3), col, 1)
            cv2.putText(out, str(vid), (int(x0), int(y0) - 5), cv2.FONT_HERSHEY_SIMPLEX, 0.4, col, 1, cv2.LINE_AA)
        return out


def _colour(vid: int) -> tuple[int, int, int]:
    h = (vid * 47) % 180
    hsv = np.uint8([[[h, 220, 255]]])
    b, g, r = cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)[0, 0]
    return int(b), int(g), int(r)


def _own_start(t: np.ndarray, y: np.ndarray) -> int:
    """Index of a new vehicle's first own trajectory point (times t, near end y): the last point j that ends
    a standstill (the points before it within STILL_M of it for STILL_S) from which the vehicle could not
    have moved off to its last point (see MAX_ACCEL_MPS2), else 0."""
    n0 = max(0, len(t) - OWN_MAX_POINTS)
    t, y = t[n0:], y[n0:]
    n = len(t)
    if n < 3:
        return 0
    far = np.abs(y[:, None] - y[None, :]) > STILL_M  # far[i, j]: point i lies outside point j's standstill
    far[np.tril_indices(n)] = False  # only earlier points i < j count
    last_far = np.where(far.any(axis=0), n - 1 - np.argmax(far[::-1], axis=0), -1)
    j = np.arange(1, n - 1)
    still_from = last_far[j] + 1  # first point of each j's standstill
    run = t[-1] - t[j]
    moved = np.abs(y[-1] - y[j])
    ok = (t[j] - t[still_from] >= STILL_S) & (moved > STILL_M) & (run > 0.0) \
        & (moved > (0.5 * MAX_ACCEL_MPS2 * run + START_SLACK_MPS) * run)
    return n0 + int(j[ok][-1]) if ok.any() else 0


def _median_step_rate(states: list[VehicleState]) -> float:
    """The median along-road speed of a near end over its steps between consecutive states."""
    t = np.array([st.t for st in states])
    y = np.array([st.y_front for st in states])
    ok = np.diff(t) > 0
    return float(np.median(np.abs(np.diff(y)[ok]) / np.diff(t)[ok])) if ok.any() else 0.0


def _released(held: list[VehicleState]) -> VehicleState:
    """The last of a new vehicle's held states, as its first report: its trajectory runs through the earlier
    held points, and it keeps the first report's `entered`. A receding vehicle's points are its rear plus as
    far as its front is now ahead of it: its length may have grown while it was held (see
    measures._Track.edie_ahead)."""
    last = held[-1]
    ahead = last.y_front - last.y_rear
    if ahead > 0.0:
        was = held[0].y_front - held[0].y_rear
        last.trajectory = ([(t, x, y - was + ahead) for t, x, y in held[0].trajectory or []]
                           + [(h.t, h.x, h.y_rear + ahead) for h in held[:-1]])
    else:
        last.trajectory = list(held[0].trajectory or []) + [(h.t, h.x, h.y_front) for h in held[:-1]]
    last.entered = held[0].entered
    return last


def _bounds(mask: np.ndarray) -> tuple[int, int, int, int] | None:
    """The bounding box (x0, y0, x1, y1; ends exclusive) of a mask's true cells; None if none."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if not len(rows):
        return None
    return int(cols[0]), int(rows[0]), int(cols[-1]) + 1, int(rows[-1]) + 1


def _zone_of(mask: np.ndarray) -> tuple[tuple[int, int, int, int], np.ndarray] | None:
    """A detector zone (ROI, its mask) for the true pixels of a mask the size of the image; None if none."""
    box = _bounds(mask)
    if box is None:
        return None
    x0, y0, x1, y1 = box
    return box, np.ascontiguousarray(mask[y0:y1, x0:x1].astype(np.uint8) * 255)
