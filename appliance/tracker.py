"""Feature tracker: per-feature constant-velocity Kalman filter in road coordinates with NCC template search.

All live features are stepped by one numba kernel over preallocated arrays (reference: kernels_ref).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from appliance.config import TrackingParams


@njit(cache=True, inline="always")
def _project(M, u, v):
    w = M[2, 0] * u + M[2, 1] * v + M[2, 2]
    return (M[0, 0] * u + M[0, 1] * v + M[0, 2]) / w, (M[1, 0] * u + M[1, 1] * v + M[1, 2]) / w


@njit(cache=True)
def extract_template(img, cx, cy, out):
    """Zero-mean, unit-norm patch around integer (cx, cy) into out; returns False on a flat patch."""
    h = out.shape[0] // 2
    s = 0.0
    for j in range(out.shape[0]):
        for i in range(out.shape[1]):
            v = float(img[cy - h + j, cx - h + i])
            out[j, i] = v
            s += v
    mean = s / (out.shape[0] * out.shape[1])
    ss = 0.0
    for j in range(out.shape[0]):
        for i in range(out.shape[1]):
            out[j, i] -= mean
            ss += out[j, i] * out[j, i]
    if ss < 1e-6:
        return False
    nrm = np.sqrt(ss)
    for j in range(out.shape[0]):
        for i in range(out.shape[1]):
            out[j, i] /= nrm
    return True


@njit(cache=True)
def init_features(img, idx, px, tmpl, ok):
    """Extract templates for new features idx at image positions px[idx]."""
    hgt, wid = img.shape
    h = tmpl.shape[1] // 2
    for k in range(idx.shape[0]):
        i = idx[k]
        cx = int(np.floor(px[i, 0] + 0.5))
        cy = int(np.floor(px[i, 1] + 0.5))
        if cx < h or cy < h or cx >= wid - h or cy >= hgt - h:
            ok[k] = False
        else:
            ok[k] = extract_template(img, cx, cy, tmpl[i])


@njit(cache=True, inline="always")
def _parabola(a, b, c):
    d = a - 2.0 * b + c
    if d >= 0.0:
        return 0.0
    off = 0.5 * (a - c) / d
    if off > 0.5:
        return 0.5
    if off < -0.5:
        return -0.5
    return off


@njit(cache=True)
def track_step(img, Hm, Hinv, off_x, off_y, dt, alive, px, s, P, tmpl, age, miss, ncc_out,
               radius, ncc_min, q_acc, sigma_px, max_acc, max_lat, max_speed, max_miss, refresh_below):
    """Predict, search, update every live feature (in place). Returns the number of matched features."""
    hgt, wid = img.shape
    T = tmpl.shape[1]
    h = T // 2
    dt2 = dt * dt
    q11 = q_acc * q_acc * dt2 * dt2 / 4.0
    q12 = q_acc * q_acc * dt2 * dt / 2.0
    q22 = q_acc * q_acc * dt2
    matched = 0
    scores = np.empty((3 * radius + 3, 3 * radius + 3))
    nT = float(T * T)
    sum1 = np.zeros((3 * radius + 4 + T, 3 * radius + 4 + T))  # running sums of the search window and its squares
    sum2 = np.zeros((3 * radius + 4 + T, 3 * radius + 4 + T))
    spt = np.empty((3 * radius + 3, 3 * radius + 3))  # each position's sum of template x patch
    for i in range(alive.shape[0]):
        if not alive[i]:
            continue
        # --- predict (constant velocity) ---
        X = s[i, 0] + dt * s[i, 2]
        Y = s[i, 1] + dt * s[i, 3]
        VX = s[i, 2]
        VY = s[i, 3]
        Pp = np.empty((4, 4))
        for a in range(4):
            for b in range(4):
                Pp[a, b] = P[i, a, b]
        # P' = F P F^T with F = [[I, dt I], [0, I]]
        for a in range(2):
            for b in range(4):
                Pp[a, b] += dt * P[i, a + 2, b]
        for a in range(4):
            for b in range(2):
                Pp[a, b] += dt * Pp[a, b + 2]
        for a in range(2):
            Pp[a, a] += q11
            Pp[a, a + 2] += q12
            Pp[a + 2, a] += q12
            Pp[a + 2, a + 2] += q22
        u, v = _project(Hinv, X, Y)
        u += off_x
        v += off_y
        # search radius from the predicted position's uncertainty in pixels (3 sigma), capped
        ua, va = _project(Hinv, X + np.sqrt(Pp[0, 0]), Y)
        ub, vb = _project(Hinv, X, Y + np.sqrt(Pp[1, 1]))
        sig_px = max(abs(ua + off_x - u) + abs(va + off_y - v), abs(ub + off_x - u) + abs(vb + off_y - v))
        r_cap = radius if age[i] >= 3 else radius + radius // 2
        r = min(r_cap, max(2, int(np.ceil(3.0 * sig_px + 1.0))))
        cx = int(np.floor(u + 0.5))
        cy = int(np.floor(v + 0.5))
        if not (np.isfinite(u) and np.isfinite(v)) or cx - r - h - 1 < 0 or cy - r - h - 1 < 0 \
                or cx + r + h + 1 >= wid or cy + r + h + 1 >= hgt:
            alive[i] = False
            continue
        # --- NCC search: normalised correlation of the zero-mean unit-norm template with each patch. The
        # patches' sums come from running sums over the window (integer grey levels: exact, so the same as
        # summing patch by patch) ---
        W = 2 * (r + h) + 1
        x0 = cx - r - h
        y0 = cy - r - h
        for j in range(W):
            rs = 0.0
            rss = 0.0
            for c in range(W):
                p = float(img[y0 + j, x0 + c])
                rs += p
                rss += p * p
                sum1[j + 1, c + 1] = sum1[j, c + 1] + rs
                sum2[j + 1, c + 1] = sum2[j, c + 1] + rss
        tm = tmpl[i]
        R = 2 * r + 1
        # the template's products summed for all positions at once, pixel by pixel in the template's order
        for a in range(R):
            for b in range(R):
                spt[a, b] = 0.0
        for j in range(T):
            for q in range(T):
                w = tm[j, q]
                for a in range(R):
                    row = img[y0 + a + j, x0 + q:x0 + q + R]
                    acc = spt[a]
                    for b in range(R):
                        acc[b] += float(row[b]) * w
        best = -2.0
        bx = 0
        by = 0
        for dy in range(-r, r + 1):
            a = dy + r
            for dx in range(-r, r + 1):
                b = dx + r
                sp = sum1[a + T, b + T] - sum1[a, b + T] - sum1[a + T, b] + sum1[a, b]
                spp = sum2[a + T, b + T] - sum2[a, b + T] - sum2[a + T, b] + sum2[a, b]
                var = spp - sp * sp / nT
                c = spt[a, b] / np.sqrt(var) if var >= 1e-6 else -1.0
                scores[a, b] = c
                if c > best:
                    best = c
                    bx = dx
                    by = dy
        accepted = best >= ncc_min
        if accepted:
            sx = 0.0
            sy = 0.0
            if -r < bx < r:
                sx = _parabola(scores[by + r, bx + r - 1], best, scores[by + r, bx + r + 1])
            if -r < by < r:
                sy = _parabola(scores[by + r - 1, bx + r], best, scores[by + r + 1, bx + r])
            mu = cx + bx + sx
            mv = cy + by + sy
            ru = mu - off_x
            rv = mv - off_y
            zx, zy = _project(Hm, ru, rv)
            ax, ay = _project(Hm, ru + 1.0, rv)
            bx2, by2 = _project(Hm, ru, rv + 1.0)
            j00 = ax - zx
            j10 = ay - zy
            j01 = bx2 - zx
            j11 = by2 - zy
            sp2 = sigma_px * sigma_px
            R00 = sp2 * (j00 * j00 + j01 * j01)
            R01 = sp2 * (j00 * j10 + j01 * j11)
            R11 = sp2 * (j10 * j10 + j11 * j11)
            S00 = Pp[0, 0] + R00
            S01 = Pp[0, 1] + R01
            S11 = Pp[1, 1] + R11
            ix = zx - X
            iy = zy - Y
            # physical gate: the jump from the prediction must be reachable under max_acc
            slack = 0.5 * max_acc * dt2
            if abs(ix) > slack + 3.0 * np.sqrt(S00) or abs(iy) > slack + 3.0 * np.sqrt(S11):
                accepted = False
        if accepted:
            det = S00 * S11 - S01 * S01
            i00 = S11 / det
            i01 = -S01 / det
            i11 = S00 / det
            K = np.empty((4, 2))
            for a in range(4):
                K[a, 0] = Pp[a, 0] * i00 + Pp[a, 1] * i01
                K[a, 1] = Pp[a, 0] * i01 + Pp[a, 1] * i11
            nX = X + K[0, 0] * ix + K[0, 1] * iy
            nY = Y + K[1, 0] * ix + K[1, 1] * iy
            nVX = VX + K[2, 0] * ix + K[2, 1] * iy
            nVY = VY + K[3, 0] * ix + K[3, 1] * iy
            if abs(nVX) > max_lat:
                accepted = False
        if not accepted:
            miss[i] += 1
            s[i, 0] = X
            s[i, 1] = Y
            for a in range(4):
                for b in range(4):
                    P[i, a, b] = Pp[a, b]
            px[i, 0] = u
            px[i, 1] = v
            ncc_out[i] = best
            # only a new corner's one-frame flow can be this fast (a match leaving it so kills it below); never
            # corrected while the corner misses, it would carry it on at that speed
            if miss[i] > max_miss or np.sqrt(VX * VX + VY * VY) > max_speed:
                alive[i] = False
            continue
        if np.sqrt(nVX * nVX + nVY * nVY) > max_speed:
            alive[i] = False
            continue
        s[i, 0] = nX
        s[i, 1] = nY
        s[i, 2] = nVX
        s[i, 3] = nVY
        # P = (I - K Hm) P'
        for a in range(4):
            for b in range(4):
                P[i, a, b] = Pp[a, b] - K[a, 0] * Pp[0, b] - K[a, 1] * Pp[1, b]
        px[i, 0] = mu
        px[i, 1] = mv
        age[i] += 1
        miss[i] = 0
        ncc_out[i] = best
        matched += 1
        if best < refresh_below:
            tcx = int(np.floor(mu + 0.5))
            tcy = int(np.floor(mv + 0.5))
            extract_template(img, tcx, tcy, tmpl[i])
    return matched


def project_points(M: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """(N, 2) points through a 3x3 homography."""
    p = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
    q = p @ M[:, :2].T + M[:, 2]
    return q[:, :2] / q[:, 2:3]


class FeatureTracker:
    """Fixed-capacity arrays of live features; ``step`` tracks them all, ``add`` starts new ones."""

    MAX_MISS = 2
    SIGMA_PX = 0.5  # NCC subpixel localisation noise (px)
    Q_ACC = 3.0  # process noise: white acceleration (m/s^2)
    REFRESH_BELOW = 0.9  # refresh a template when the match gets weaker than this (appearance change)

    def __init__(self, params: TrackingParams, H: np.ndarray, Hinv: np.ndarray) -> None:
        n, T = params.max_features, params.template_px
        self.p = params
        self.H = np.ascontiguousarray(H, dtype=np.float64)
        self.Hinv = np.ascontiguousarray(Hinv, dtype=np.float64)
        self.alive = np.zeros(n, np.bool_)
        self.fid = np.full(n, -1, np.int64)
        self.px = np.zeros((n, 2))
        self.s = np.zeros((n, 4))
        self.P = np.zeros((n, 4, 4))
        self.tmpl = np.zeros((n, T, T), np.float32)
        self.age = np.zeros(n, np.int32)
        self.miss = np.zeros(n, np.int32)
        self.ncc = np.zeros(n, np.float32)
        self.lane = np.zeros(n, np.int32)
        self.born_t = np.zeros(n)
        self.born_s = np.zeros((n, 2))
        self.born_px = np.zeros((n, 2))  # stabilised image position at birth
        self.max_disp = np.zeros(n)  # largest image displacement from birth (px, stabilised)
        self.vmax = np.zeros(n)  # highest settled along-road speed so far (m/s) ...
        self.t_vmax = np.zeros(n)  # ... and when it was last reached
        self.next_id = 0
        self.max_speed = params.max_speed_kmh / 3.6

    @property
    def capacity(self) -> int:
        return self.alive.shape[0]

    def live(self) -> np.ndarray:
        return np.flatnonzero(self.alive)

    def step(self, img: np.ndarray, offset: tuple[float, float], dt: float) -> int:
        """Track all live features into ``img`` (uint8) after ``dt`` seconds; image shift ``offset``."""
        if not self.alive.any():
            return 0
        p = self.p
        n = track_step(
            img, self.H, self.Hinv, float(offset[0]), float(offset[1]), float(dt), self.alive, self.px, self.s,
            self.P, self.tmpl, self.age, self.miss, self.ncc, int(p.search_radius_px), float(p.ncc_min),
            self.Q_ACC, self.SIGMA_PX, float(p.max_accel_mps2), float(p.max_lateral_mps), self.max_speed,
            self.MAX_MISS, self.REFRESH_BELOW,
        )
        live = self.live()
        d = np.abs(self.px[live] - np.asarray(offset) - self.born_px[live]).max(axis=1)
        self.max_disp[live] = np.maximum(self.max_disp[live], d)
        return n

    def add(self, img: np.ndarray, px: np.ndarray, prev_px: np.ndarray | None, offset: tuple[float, float],
            dt: float, t: float, lanes: np.ndarray) -> np.ndarray:
        """Start features at image points px (N, 2); prev_px are their positions one frame earlier
        (for the initial velocity), or None. Returns the slots used."""
        free = np.flatnonzero(~self.alive)[: len(px)]
        k = len(free)
        if k == 0:
            return free
        px = np.asarray(px[:k], dtype=np.float64)
        off = np.asarray(offset, dtype=np.float64)
        road = project_points(self.H, px - off)
        self.px[free] = px
        ok = np.zeros(k, np.bool_)
        init_features(img, free.astype(np.int64), self.px, self.tmpl, ok)
        vel = np.zeros((k, 2))
        if prev_px is not None and dt > 0:
            road_prev = project_points(self.H, np.asarray(prev_px[:k], dtype=np.float64) - off)
            vel = (road - road_prev) / dt
        mpp = np.abs(project_points(self.H, px - off + [0.0, 1.0]) - road)  # road metres per image row
        self.s[free, :2] = road
        self.s[free, 2:] = vel
        self.P[free] = 0.0
        sig_pos = np.maximum(mpp.max(axis=1), 0.02)
        for a in range(2):
            self.P[free, a, a] = sig_pos**2
        # velocity from one frame of motion: as uncertain as two positions over dt, plus model slack
        sig_v = np.sqrt(2.0) * sig_pos / max(dt, 1e-3) + 1.0
        self.P[free, 2, 2] = sig_v**2
        self.P[free, 3, 3] = sig_v**2
        self.age[free] = 0
        self.miss[free] = 0
        self.ncc[free] = 1.0
        self.lane[free] = lanes[:k]
        self.born_t[free] = t
        self.born_s[free] = road
        self.born_px[free] = px - off
        self.max_disp[free] = 0.0
        self.vmax[free] = 0.0
        self.t_vmax[free] = t
        self.fid[free] = np.arange(self.next_id, self.next_id + k)
        self.next_id += k
        self.alive[free] = ok
        return free[ok]

    def kill(self, slots: np.ndarray) -> None:
        self.alive[slots] = False
