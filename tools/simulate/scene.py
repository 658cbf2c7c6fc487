"""One synthetic scene: camera, road, static background, traffic, exact truth, and frame rendering."""

from __future__ import annotations

import math

import cv2
import numpy as np

from tools.simulate.background import render_background, shadow_points
from tools.simulate.camera import Camera
from tools.simulate.conditions import Conditions
from tools.simulate.presets import SceneParams, scene_params
from tools.simulate.raster import fill_quads
from tools.simulate.road import RoadLayout
from tools.simulate.traffic import Traffic, lane_at_x
from tools.simulate.truth import START_WALL, StepState, TruthAccumulator, TruthLane, TruthLoop
from tools.simulate.vehicles import build_shape

LOOP_LENGTH_M = 1.8
CURVE_STEP_M = 5.0  # vertex spacing of a curved lane polygon: chord error step^2 / 8R < 1.6 cm for |R| >= 200 m
WARM_UP_S = 90.0
FAR_DETAIL_M = 110.0
NIGHT_EXPOSURE = 0.28
# corner indices of the six faces of a box built by vehicles._box (index = 4 z + 2 u + x)
BOX_FACES = np.array([[0, 1, 3, 2], [4, 5, 7, 6], [0, 1, 5, 4], [2, 3, 7, 6], [0, 2, 6, 4], [1, 3, 7, 5]])


class Scene:
    """Build with a preset name and seed; then alternate `step(dt)` and `render()`."""

    def __init__(self, preset: str, seed: int, *, width: int = 640, height: int = 480, fps: float = 25.0,
                 period_s: float = 300.0, truth: bool = True, **overrides: object):
        self.preset, self.seed, self.fps = preset, int(seed), float(fps)
        self.keep_truth = truth
        if width < 64 or height < 48:
            raise ValueError(f"image size {width}x{height} is too small (at least 64x48)")
        if not 0 < fps <= 240:
            raise ValueError(f"fps must be in (0, 240], got {fps}")
        self.p: SceneParams = scene_params(preset, **overrides)
        p = self.p
        streams = np.random.SeedSequence(self.seed).spawn(4)
        self.rng_traffic, rng_bg, rng_cond, self.rng_shape = (np.random.default_rng(s) for s in streams)
        self.layout = RoadLayout.make(p.lanes_approaching, p.lanes_receding, p.lane_width_m, p.curve_radius_m)
        cam_x = self.layout.x_max + p.cam_offset_m
        aim_x = float(self.layout.centre_x(60.0)) - cam_x
        pan = p.cam_pan_deg if p.cam_pan_deg is not None else math.degrees(math.atan2(aim_x, 60.0))
        self.cam = Camera(width, height, p.focal_scale * width, p.cam_height_m, p.cam_tilt_deg, pan, cam_x)
        el, az = math.radians(p.sun_elevation_deg), math.radians(p.sun_azimuth_deg)
        self.sun = np.array([math.cos(el) * math.sin(az), math.cos(el) * math.cos(az), math.sin(el)])
        self.ambient = 0.85 if (p.overcast or p.night or p.dusk) else 0.5
        self.exposure = NIGHT_EXPOSURE if p.night else 0.4 if p.dusk else 0.8 if p.overcast else 1.0
        self.shadows = p.shadows and not (p.overcast or p.night or p.dusk)
        light = self.sun * (0.35 if p.overcast else 1.0)
        lamp_ys = [28.0, 68.0, 108.0, 148.0]
        stop_y = p.signal[0] if p.signal else None
        self.bg, self.bg_shadow, self.objects = render_background(
            self.cam, self.layout, rng_bg, sun=self.sun, ambient=self.ambient, shadows=self.shadows, night=p.night,
            exposure=self.exposure, wet=p.rain, stop_line_y=stop_y, lamp_ys=lamp_ys)
        self.objects.sort(key=lambda o: o.depth, reverse=True)  # painter's order among static objects
        self.veh_scale = 1.0
        for o in self.objects:  # baked in; pasted again only over vehicles farther away than the object
            self._paste(self.bg, o)
            self._paste(self.bg_shadow, o)
        self._obj_box = np.array([[o.x0, o.y0, o.x0 + o.patch.shape[1], o.y0 + o.patch.shape[0]] for o in self.objects],
                                 dtype=np.float64).reshape(-1, 4)
        self._obj_depth = np.array([o.depth for o in self.objects])
        self.night_lights = p.night or p.dusk
        self.bg_night = None
        self.veh_scale, self.lamps_dynamic = 1.0, False
        if p.day_to_night:  # a second, night version of the same background to fade into
            if len(p.day_to_night) != 2 or not 0 <= p.day_to_night[0] < p.day_to_night[1]:
                raise ValueError(f"day_to_night must be [t_start, t_end] with 0 <= t_start < t_end, got {p.day_to_night}")
            self.bg_night, _, _ = render_background(
                self.cam, self.layout, np.random.default_rng(streams[1]), sun=self.sun, ambient=0.85, shadows=False,
                night=True, exposure=NIGHT_EXPOSURE, wet=p.rain, stop_line_y=stop_y, lamp_ys=lamp_ys)
            self.bg_day, self.bg_shadow_day = self.bg, self.bg_shadow
            self.lamps_dynamic = True
        build_night, build_exp = (False, 1.0) if p.day_to_night else (self.night_lights, self.exposure)
        self.traffic = Traffic(p, self.layout, self.rng_traffic, lambda c, d: build_shape(
            c, self.rng_shape, d, light, self.ambient, build_night, build_exp))
        self.conditions = Conditions(p, width, height, rng_cond)
        self.geometry = self._site_geometry()
        self.truth = TruthAccumulator(
            [TruthLane(g["id"], g["dir"], tuple(g["region"]), g["count_y"]) for g in self.geometry["lanes"]],
            [TruthLoop(lp["id"], lp["channel"], lp["lane"], lp["y_m"], lp["length_m"]) for lp in self.geometry["loops"]],
            period_s=period_s, start_wall=START_WALL)
        self.traffic.warm_up(WARM_UP_S)
        self._mask = np.zeros((height, width), np.uint8)
        self._beam = np.zeros((height, width), np.uint8)
        self._idbuf = np.zeros((height // 2, width // 2), np.uint16)
        for o in self.objects:
            o.mask_half = cv2.resize(o.mask, (max(1, o.mask.shape[1] // 2), max(1, o.mask.shape[0] // 2)),
                                     interpolation=cv2.INTER_NEAREST) > 0

    @property
    def t(self) -> float:
        return self.traffic.t

    # -- site geometry ---------------------------------------------------------------------------------
    def _site_geometry(self) -> dict:
        cam, W, H = self.cam, self.cam.width, self.cam.height_px
        m = 3.0
        ys = np.arange(1.0, 300.0, 0.25)

        def inside(px: np.ndarray) -> np.ndarray:
            return (px[:, 0] >= m) & (px[:, 0] <= W - 1 - m) & (px[:, 1] >= m) & (px[:, 1] <= H - 1 - m)

        lanes, loops = [], []
        lay = self.layout
        for ln in lay.lanes:
            a = cam.road_to_image(lay.to_road(ln.x0, ys))
            b = cam.road_to_image(lay.to_road(ln.x1, ys))
            ok = inside(a) & inside(b)
            width_px = np.abs(b[:, 0] - a[:, 0])
            if not ok.any():
                raise ValueError(f"lane {ln.id} is not in view; change the camera (pan/tilt/height)")
            first = int(np.argmax(ok))
            run = ok[first:] & (width_px[first:] >= 12.0)
            last = first + (int(np.argmin(run)) - 1 if not run.all() else len(run) - 1)
            y_lo, y_hi = float(ys[first]), min(float(ys[last]), 220.0)
            wide = np.nonzero(ok & (width_px >= 20.0))[0]
            r_hi = min(float(ys[wide[-1]]) if len(wide) else y_hi, y_lo + 100.0, y_hi)
            region = [round(y_lo + 0.5, 2), round(r_hi, 2)]
            count_y = round(region[0] + 0.3 * (region[1] - region[0]), 2)
            if lay.curved:  # both edges sampled along the bend (every CURVE_STEP_M), up one side, down the other
                yv = np.linspace(y_lo, y_hi, max(2, int(math.ceil((y_hi - y_lo) / CURVE_STEP_M)) + 1))
                polygon = np.vstack([lay.to_road(ln.x0, yv)[::-1], lay.to_road(ln.x1, yv)]).tolist()
            else:
                polygon = [[ln.x0, y_lo], [ln.x1, y_lo], [ln.x1, y_hi], [ln.x0, y_hi]]
            lanes.append(dict(id=ln.id, dir=ln.direction, x0=ln.x0, x1=ln.x1, polygon=polygon,
                              region=region, count_y=count_y))
            loops.append(dict(id=f"L{ln.id}", lane=ln.id, channel=ln.id,
                              y_m=round(count_y - LOOP_LENGTH_M / 2, 2), length_m=LOOP_LENGTH_M))
        # calibration: lane boundary points at three distances
        y_near = max(min(p[1] for p in g["polygon"]) for g in lanes) + 1.0
        y_far = min(max(p[1] for p in g["polygon"]) for g in lanes)
        xs = sorted({self.layout.x_min, self.layout.x_max, self.layout.lanes[len(self.layout.lanes) // 2].x0})
        road, img = [], []
        for y in (y_near, 0.6 * y_near + 0.4 * y_far, y_far):
            for x in xs:
                x = float(lay.to_road(x, y)[0, 0])
                px = cam.road_to_image(np.array([[x, y]]))[0]
                if inside(px[None])[0]:
                    road.append([round(float(x), 3), round(float(y), 3)])
                    img.append([round(float(px[0]), 3), round(float(px[1]), 3)])
        # fiducials: static high-texture points well inside the image
        fid = []
        per_kind = {"sign": 4, "lamp": 2, "post": 2}
        for kind in ("sign", "lamp", "post"):
            objs = sorted((o for o in self.objects if o.name.startswith(kind) and not o.name.startswith("ground")),
                          key=lambda o: o.depth)
            taken = 0
            for o in objs:
                for (u, v) in o.fiducials:
                    if 16 <= u <= W - 17 and 16 <= v <= H - 17 and taken < per_kind[kind]:
                        fid.append([round(float(u), 2), round(float(v), 2)])
                        taken += 1
        return dict(lanes=lanes, loops=loops, calibration=dict(image_px=img, road_m=road), fiducials=fid)

    def site_dict(self, url: str, *, name: str | None = None) -> dict:
        """The site configuration (appliance.config format) for this scene's camera."""
        g = self.geometry
        return {
            "site": {"name": name or f"synthetic {self.preset} seed {self.seed}",
                     "description": f"roadwatch simulate --preset {self.preset} --seed {self.seed}"},
            "source": {"url": url, "width": self.cam.width, "height": self.cam.height_px, "fps": self.fps},
            "calibration": g["calibration"],
            "lanes": [{"id": ln["id"], "direction": "approaching" if ln["dir"] < 0 else "receding",
                       "polygon_m": [[round(float(a), 3), round(float(b), 3)] for a, b in ln["polygon"]],
                       "region_y_m": ln["region"], "count_y_m": ln["count_y"]} for ln in g["lanes"]],
            "loops": [dict(lp) for lp in g["loops"]],
            "fiducials": g["fiducials"],
            "measures": {"period_s": int(self.truth.period_s)},
        }

    # -- simulation -------------------------------------------------------------------------------------
    def step(self, dt: float) -> None:
        """Advance traffic by dt and accumulate the exact truth over the step."""
        tr = self.traffic
        t0 = tr.t
        tr.step(dt)
        if not self.keep_truth:
            return
        if len(tr.s):
            d = tr.dirs[tr.lane]
            y0 = tr.y_start[tr.lane]
            yf0, yf1 = y0 + d * tr.s_prev, y0 + d * tr.s
            st = StepState(tr.id, lane_at_x(self.layout, tr.x), lane_at_x(self.layout, tr.x_prev), d,
                           yf0, yf1, tr.length, tr.cls)
            if self.layout.curved:  # the body lies along the tangent at its front: its Y extent is L cos(heading)
                st.span, st.span_prev = tr.length * self._cos(yf1), tr.length * self._cos(yf0)
            self.truth.step(t0, tr.t, st)
        else:
            self.truth.step(t0, tr.t, StepState(*(np.zeros(0),) * 7, []))

    # -- rendering --------------------------------------------------------------------------------------
    def render(self, want_truth: bool = True) -> tuple[np.ndarray, list[dict]]:
        """Draw the current state: (grey image, per-vehicle truth rows without frame/t)."""
        cam, tr = self.cam, self.traffic
        if self.bg_night is not None:
            self._set_daylight(tr.t)
        img = self.bg.copy()
        n = len(tr.s)
        rows: list[dict] = []
        if n == 0:
            return self.conditions.apply(img, tr.t, self.conditions.offset(tr.t)), rows
        yf = tr.y_front()
        d = tr.dirs[tr.lane]
        lane_ids = lane_at_x(self.layout, tr.x)
        curved = self.layout.curved
        if curved:  # front centre on the bent lane, body along the tangent there
            xw = tr.x + self.layout.centre_x(yf)
            cs = self._cos(yf)
            sn = self.layout.slope(yf) * cs
            yc = yf - d * tr.length / 2 * cs
        else:
            xw, cs, sn = tr.x, None, None
            yc = yf - d * tr.length / 2
        show = (yc > 2.0) & (yc < 300.0)
        idx = np.nonzero(show)[0]
        offs = np.column_stack([xw, yf, np.zeros(n)])
        shapes = [tr.shapes[i] for i in idx]
        nq = np.array([len(sh.quads) for sh in shapes], dtype=np.int64)
        npt = np.array([len(sh.corners) for sh in shapes], dtype=np.int64)
        if len(idx):
            allq = np.concatenate([sh.quads for sh in shapes])
            alln = np.concatenate([sh.normals for sh in shapes])
            allv = np.concatenate([sh.values for sh in shapes])
            corners = np.concatenate([sh.corners for sh in shapes])
            if curved:
                allq = _turn(allq, np.repeat(cs[idx], nq)[:, None], np.repeat(sn[idx], nq)[:, None])
                alln = _turn(alln, np.repeat(cs[idx], nq), np.repeat(sn[idx], nq))
                corners = _turn(corners, np.repeat(cs[idx], npt), np.repeat(sn[idx], npt))
            allq = allq + np.repeat(offs[idx], nq, axis=0)[:, None, :]
            corners = corners + np.repeat(offs[idx], npt, axis=0)
            qpx, qdep = cam.project(allq)
            facing = np.einsum("ij,ij->i", alln, allq.mean(axis=1) - cam.centre) < 0
            facing &= (qdep > 0.5).all(axis=1)
            # level of detail: far vehicles (a few pixels) are drawn without their face details
            far = np.hypot(xw[idx] - cam.x_m, yc[idx]) > FAR_DETAIL_M
            if far.any():
                decal = np.concatenate([sh.decal for sh in shapes])
                facing &= ~(decal & np.repeat(far, nq))
            cpx, cdep = cam.project(corners)
        q_end, c_end = np.cumsum(nq), np.cumsum(npt)
        if self.shadows and len(idx):
            # a box's shadow is the union of its faces' shadows: 6 ground quads per part, one kernel call
            self._mask.fill(0)
            sp = shadow_points(corners, self.sun)
            _, sdep = cam.project(np.column_stack([sp, np.zeros(len(sp))]))
            part_ok = (sdep.reshape(-1, 8) > 0.5).all(axis=1)  # shadow wholly in front of the camera
            squads = cam.road_to_image(sp).reshape(-1, 8, 2)[:, BOX_FACES].reshape(-1, 4, 2)
            sel = np.nonzero(np.repeat(part_ok, len(BOX_FACES)))[0]
            fill_quads(self._mask, squads, self._shadow_vals(len(squads)), sel)
            cv2.copyTo(self.bg_shadow, self._mask, img)
        if self.p.rain and len(idx):
            self._reflections(img, allq, alln, allv)
        if self.night_lights and len(idx):
            self._beam.fill(0)
            for k, i in enumerate(idx):
                w = tr.shapes[i].width / 2
                for reach, level in ((35.0, 14), (22.0, 28), (12.0, 45)):  # the beam fades with distance
                    y2 = yf[i] + d[i] * reach
                    spread = 2.0 * reach / 35.0
                    poly = np.array([[tr.x[i] - w, yf[i]], [tr.x[i] + w, yf[i]],
                                     [tr.x[i] + w + spread, y2], [tr.x[i] - w - spread, y2]])
                    if curved:
                        poly[:, 0] += self.layout.centre_x(poly[:, 1])
                    if (poly[:, 1] > 3.0).all():
                        cv2.fillConvexPoly(self._beam, np.round(cam.road_to_image(poly) * 16).astype(np.int32),
                                           level, cv2.LINE_8, 4)
            cv2.add(img, cv2.blur(self._beam, (15, 15)), dst=img)
        if len(idx):
            vis_arr = np.nonzero(facing)[0]
            vis_lo = np.searchsorted(vis_arr, q_end - nq).tolist()
            vis_hi = np.searchsorted(vis_arr, q_end).tolist()
            if self.lamps_dynamic:
                allv = allv * self.veh_scale
                if self.night_lights:
                    lamp = np.concatenate([sh.lamp for sh in shapes])
                    allv = np.where(lamp > 0, lamp, allv)
        depth = np.hypot(xw[idx] - cam.x_m, yc[idx])
        objs = []
        if len(idx):
            starts = c_end - npt
            vx0 = np.minimum.reduceat(cpx[:, 0], starts)
            vx1 = np.maximum.reduceat(cpx[:, 0], starts)
            vy0 = np.minimum.reduceat(cpx[:, 1], starts)
            vy1 = np.maximum.reduceat(cpx[:, 1], starts)
            in_front = (np.minimum.reduceat(cdep, starts) > 0.5).tolist()
            hull_pts = np.round(cpx * 8).astype(np.int32)  # half resolution, 4 bits subpixel
        else:  # an empty road: no vehicle boxes
            vx0 = vx1 = vy0 = vy1 = np.zeros(0)
        if len(idx) and len(self.objects):
            ob = self._obj_box
            hit = ((vx1[:, None] >= ob[None, :, 0]) & (vx0[:, None] <= ob[None, :, 2])
                   & (vy1[:, None] >= ob[None, :, 1]) & (vy0[:, None] <= ob[None, :, 3])
                   & (depth[:, None] > self._obj_depth[None, :]))
            objs = np.nonzero(hit.any(axis=0))[0].tolist()
        order = sorted([(float(depth[k]), 0, k) for k in range(len(idx))]
                       + [(self.objects[j].depth, 1, j) for j in objs], reverse=True)
        if want_truth:
            self._idbuf.fill(0)
        hulls = {}
        batch: list[np.ndarray] = []  # visible quads of consecutive vehicles, drawn in one kernel call
        for _, kind, k in order:
            if kind == 1:
                if batch:
                    fill_quads(img, qpx, allv, np.concatenate(batch))
                    batch = []
                o = self.objects[k]
                self._paste(img, o)
                if want_truth:
                    y0, x0 = o.y0 // 2, o.x0 // 2
                    mh = o.mask_half
                    roi = self._idbuf[y0 : y0 + mh.shape[0], x0 : x0 + mh.shape[1]]
                    roi[mh[: roi.shape[0], : roi.shape[1]]] = 65535
                continue
            batch.append(vis_arr[vis_lo[k] : vis_hi[k]])
            if want_truth:
                if not in_front[k]:
                    continue
                hull = cv2.convexHull(hull_pts[starts[k] : c_end[k]])
                cv2.fillConvexPoly(self._idbuf, hull, k + 1, cv2.LINE_8, 4)
                hulls[k] = hull
        if batch:
            fill_quads(img, qpx, allv, np.concatenate(batch))
        if self.night_lights:
            self._lights(img, idx, offs, d, cs, sn)
        dxy = self.conditions.offset(tr.t)
        out = self.conditions.apply(img, tr.t, dxy)
        if want_truth:
            counts = np.bincount(self._idbuf.ravel(), minlength=len(idx) + 1).tolist()
            W, H = cam.width, cam.height_px
            bx0, bx1 = (vx0 + dxy[0]).tolist(), (vx1 + dxy[0]).tolist()
            by0, by1 = (vy0 + dxy[1]).tolist(), (vy1 + dxy[1]).tolist()
            cols = {name: arr[idx].tolist() for name, arr in (
                ("id", tr.id), ("lane", lane_ids), ("x", xw), ("yf", yf), ("yc", yc), ("v", tr.v), ("a", tr.a),
                ("len", tr.length), ("d", d), ("span", tr.length * cs if curved else tr.length))}
            for k, hull in hulls.items():
                x0, x1, y0, y1 = bx0[k], bx1[k], by0[k], by1[k]
                if x1 < 0 or y1 < 0 or x0 > W - 1 or y0 > H - 1:
                    continue
                h = hull.astype(np.float32) / 16.0
                area = cv2.contourArea(h) + 0.5 * cv2.arcLength(h, True)
                rows.append({
                    "vehicle_id": cols["id"][k], "class": tr.cls[idx[k]], "lane": cols["lane"][k], "x_m": cols["x"][k],
                    "y_front_m": cols["yf"][k], "y_rear_m": cols["yf"][k] - cols["d"][k] * cols["span"][k],
                    "y_centre_m": cols["yc"][k], "speed_mps": cols["v"][k], "accel_mps2": cols["a"][k],
                    "length_m": cols["len"][k], "bbox_x0": max(x0, 0.0), "bbox_y0": max(y0, 0.0),
                    "bbox_x1": min(x1, W - 1.0), "bbox_y1": min(y1, H - 1.0),
                    "visible_frac": min(1.0, counts[k + 1] / max(area, 1.0)),
                })
        return out, rows

    def _shadow_vals(self, n: int) -> np.ndarray:
        if getattr(self, "_svals", None) is None or len(self._svals) < n:
            self._svals = np.full(max(n, 512), 255.0)
        return self._svals

    def _set_daylight(self, t: float) -> None:
        """Fade from day to night: background, shadows, vehicle shading, lights and the camera's gain target."""
        t0, t1 = self.p.day_to_night
        f = float(np.clip((t - t0) / (t1 - t0), 0.0, 1.0))
        self.night_factor = f
        self.bg = cv2.addWeighted(self.bg_day, 1.0 - f, self.bg_night, f, 0.0)
        self.shadows = self.p.shadows and f < 0.6
        if self.shadows:
            self.bg_shadow = cv2.addWeighted(self.bg_shadow_day, 1.0 - f, self.bg_night, f, 0.0)
        self.veh_scale = (1.0 - f) + f * NIGHT_EXPOSURE
        self.night_lights = f > 0.4
        self.conditions.night_factor = f

    def _reflections(self, img: np.ndarray, quads: np.ndarray, normals: np.ndarray, values: np.ndarray) -> None:
        """Crude wet-road mirror images: the vehicles reflected in the road plane, faint and dark."""
        mq = quads.copy()
        mq[..., 2] *= -1.0
        mn = normals * np.array([1.0, 1.0, -1.0])
        px, dep = self.cam.project(mq)
        facing = (np.einsum("ij,ij->i", mn, mq.mean(axis=1) - self.cam.centre) < 0) & (dep > 0.5).all(axis=1)
        pts = np.round(px * 16).astype(np.int32)
        road = 0.72 * 70.0 * self.exposure + 30.0
        vals = (0.25 * values + 0.75 * road).tolist()
        for qi in np.nonzero(facing)[0].tolist():
            cv2.fillConvexPoly(img, pts[qi], vals[qi], cv2.LINE_8, 4)

    def _paste(self, img: np.ndarray, o) -> None:
        roi = img[o.y0 : o.y0 + o.patch.shape[0], o.x0 : o.x0 + o.patch.shape[1]]
        patch = o.patch if self.veh_scale == 1.0 else cv2.convertScaleAbs(o.patch, alpha=self.veh_scale)
        cv2.copyTo(patch, o.mask, roi)

    def _cos(self, y: np.ndarray) -> np.ndarray:
        """cos(heading) of a vehicle whose front is at Y on the curved road."""
        s = self.layout.slope(y)
        return 1.0 / np.sqrt(1.0 + s * s)

    def _lights(self, img: np.ndarray, idx: np.ndarray, offs: np.ndarray, d: np.ndarray,
                cs: np.ndarray | None = None, sn: np.ndarray | None = None) -> None:
        tr, cam = self.traffic, self.cam
        pts, sizes = [], []
        for i in idx:
            sh = tr.shapes[i]
            if not len(sh.lights):
                continue
            facing = sh.light_front if d[i] < 0 else ~sh.light_front  # lights on the face towards the camera
            L = sh.lights[facing] if cs is None else _turn(sh.lights[facing], cs[i], sn[i])
            L = L + offs[i]
            px, dep = cam.project(L)
            good = dep > 1.0
            pts.extend(px[good])
            base = 9.0 if d[i] < 0 else 4.0
            sizes.extend(np.clip(base * 25.0 / dep[good], 2, 11))
        if pts:
            self.conditions.glare(img, np.array(pts), np.array(sizes))


def _turn(p: np.ndarray, c, s) -> np.ndarray:
    """Points/vectors (..., 3) of the straight frame turned to a heading with cos c, sin s (+ towards +X)."""
    out = p.copy()
    out[..., 0] = p[..., 0] * c + p[..., 1] * s
    out[..., 1] = p[..., 1] * c - p[..., 0] * s
    return out
