"""Microscopic traffic: IDM car following per lane, MOBIL-like lane changes, Poisson demand, a signal."""

from __future__ import annotations

from typing import Callable

import numpy as np

from tools.simulate.presets import SceneParams
from tools.simulate.road import RoadLayout
from tools.simulate.vehicles import CLASS_IDM, Shape

S0 = 2.0  # IDM jam distance (m)
LC_SPEED = 1.1  # lateral speed during a lane change (m/s)


class Traffic:
    """All vehicles as arrays; `step(dt)` advances them. Positions s are metres along the lane direction."""

    def __init__(self, params: SceneParams, layout: RoadLayout, rng: np.random.Generator,
                 shape_factory: Callable[[str, int], Shape]):
        self.p, self.layout, self.rng = params, layout, rng
        self.shape_factory = shape_factory  # (cls, direction) -> Shape
        self.t = 0.0
        self.next_id = 1
        n = 0
        self.id = np.zeros(n, np.int64)
        self.lane = np.zeros(n, np.int64)  # lane index the vehicle follows in (target lane while changing)
        self.s = np.zeros(n)
        self.s_prev = np.zeros(n)
        self.v = np.zeros(n)
        self.a = np.zeros(n)
        self.length = np.zeros(n)
        self.v0 = np.zeros(n)
        self.amax = np.zeros(n)
        self.bcomf = np.zeros(n)
        self.x = np.zeros(n)
        self.x_prev = np.zeros(n)
        self.lc_until = np.zeros(n)
        self.cls: list[str] = []
        self.shapes: list[Shape] = []
        self.classes = list(params.class_mix)
        w = np.array([params.class_mix[c] for c in self.classes], dtype=np.float64)
        self.class_p = w / w.sum()
        nl = len(layout.lanes)
        fac = list(params.lane_demand_factors) + [1.0] * nl
        self.next_arrival = np.array([rng.exponential(3600.0 / max(params.demand_vph * fac[k], 1e-6)) for k in range(nl)])
        self.pending = np.zeros(nl, np.int64)
        self.dirs = np.array([ln.direction for ln in layout.lanes])
        self.y_start = np.array([ln.y_start for ln in layout.lanes])
        self.s_end = np.array([abs(ln.y_end - ln.y_start) for ln in layout.lanes])
        self._next_lc_check = 0.0

    # -- demand ----------------------------------------------------------------------------------
    def demand_factor(self, t: float) -> float:
        prof = self.p.demand_profile
        if not prof:
            return 1.0
        ts = [q[0] for q in prof]
        fs = [q[1] for q in prof]
        return float(np.interp(t, ts, fs))

    def signal_red(self, t: float) -> bool:
        sig = self.p.signal
        if not sig:
            return False
        _, cycle, red = sig
        return (t % cycle) < red

    # -- geometry helpers --------------------------------------------------------------------------
    def y_front(self, s: np.ndarray | None = None) -> np.ndarray:
        s = self.s if s is None else s
        d = self.dirs[self.lane]
        return self.y_start[self.lane] + d * s

    def _spawn(self, lane_idx: int) -> bool:
        in_lane = np.nonzero(self.lane == lane_idx)[0]
        v_lim = self.p.speed_limit_kmh / 3.6
        v_new = v_lim
        if len(in_lane):
            last = in_lane[np.argmin(self.s[in_lane])]
            rear = self.s[last] - self.length[last]
            v_new = min(v_lim, self.v[last] + 2.0)
            need = S0 + v_new * self.p.idm_headway_s * 0.9
            if rear < need:
                return False
        cls = str(self.rng.choice(self.classes, p=self.class_p))
        ln = self.layout.lanes[lane_idx]
        shape = self.shape_factory(cls, ln.direction)
        amax, b, vf = CLASS_IDM[cls]
        v0 = v_lim * vf * self.rng.uniform(0.9, 1.1)
        x = ln.xc + self.rng.normal(0.0, 0.15)
        self.id = np.append(self.id, self.next_id)
        self.next_id += 1
        self.lane = np.append(self.lane, lane_idx)
        self.s = np.append(self.s, 0.0)
        self.s_prev = np.append(self.s_prev, 0.0)
        self.v = np.append(self.v, min(v_new, v0))
        self.a = np.append(self.a, 0.0)
        self.length = np.append(self.length, shape.length)
        self.v0 = np.append(self.v0, v0)
        self.amax = np.append(self.amax, amax)
        self.bcomf = np.append(self.bcomf, b)
        self.x = np.append(self.x, x)
        self.x_prev = np.append(self.x_prev, x)
        self.lc_until = np.append(self.lc_until, -1.0)
        self.cls.append(cls)
        self.shapes.append(shape)
        return True

    def _remove(self, keep: np.ndarray) -> None:
        for name in ("id", "lane", "s", "s_prev", "v", "a", "length", "v0", "amax", "bcomf", "x", "x_prev", "lc_until"):
            setattr(self, name, getattr(self, name)[keep])
        idx = np.nonzero(keep)[0]
        self.cls = [self.cls[i] for i in idx]
        self.shapes = [self.shapes[i] for i in idx]

    # -- car following -------------------------------------------------------------------------------
    def _leaders(self) -> tuple[np.ndarray, np.ndarray]:
        """Gap to and speed of the vehicle ahead in the same lane (inf gap when none)."""
        n = len(self.s)
        gap = np.full(n, np.inf)
        vl = np.zeros(n)
        if n == 0:
            return gap, vl
        order = np.lexsort((self.s, self.lane))
        same = self.lane[order[1:]] == self.lane[order[:-1]]
        f, lead = order[:-1][same], order[1:][same]
        gap[f] = self.s[lead] - self.length[lead] - self.s[f]
        vl[f] = self.v[lead]
        return gap, vl

    def _idm(self, v, v0, amax, b, gap, vl) -> np.ndarray:
        T = self.p.idm_headway_s
        sstar = S0 + np.maximum(0.0, v * T + v * (v - vl) / (2.0 * np.sqrt(amax * b)))
        g = np.maximum(gap, 0.1)
        return amax * (1.0 - (v / v0) ** 4 - (sstar / g) ** 2)

    def step(self, dt: float) -> None:
        """Advance the traffic by dt seconds (spawn, follow, change lanes, leave)."""
        t1 = self.t + dt
        lam = self.demand_factor(self.t)
        factors = self.p.lane_demand_factors
        for k in range(len(self.layout.lanes)):
            f = factors[k] if k < len(factors) else 1.0
            while self.next_arrival[k] <= t1:
                self.pending[k] += 1
                rate = max(self.p.demand_vph * lam * f, 1e-3) / 3600.0
                self.next_arrival[k] += self.rng.exponential(1.0 / rate)
            if self.pending[k] > 0 and self._spawn(k):
                self.pending[k] -= 1
        self.s_prev = self.s.copy()
        self.x_prev = self.x.copy()
        gap, vl = self._leaders()
        if self.p.signal and self.signal_red(self.t) and len(self.s):
            stop_y = self.p.signal[0]
            s_stop = (stop_y - self.y_start[self.lane]) * self.dirs[self.lane]
            appr = self.dirs[self.lane] < 0
            to_stop = s_stop - self.s
            can_stop = to_stop > self.v**2 / (2 * 5.0)
            use = appr & (to_stop > -0.5) & can_stop & (to_stop < gap)
            gap = np.where(use, to_stop, gap)
            vl = np.where(use, 0.0, vl)
        a = self._idm(self.v, self.v0, self.amax, self.bcomf, gap, vl)
        a = np.clip(a, -9.0, self.amax)
        v_new = np.maximum(self.v + a * dt, 0.0)
        ds = 0.5 * (self.v + v_new) * dt
        ds = np.minimum(ds, np.maximum(gap - 0.3, 0.0))  # never drive into the leader
        self.a = (v_new - self.v) / dt if dt > 0 else a
        self.v = v_new
        self.s = self.s + ds
        # lateral motion towards the lane centre (lane changes)
        target = np.array([self.layout.lanes[k].xc for k in self.lane]) if len(self.lane) else np.zeros(0)
        dx = np.clip(target - self.x, -LC_SPEED * dt, LC_SPEED * dt)
        self.x = self.x + np.where(np.abs(target - self.x) > 0.2, dx, 0.0)
        self.t = t1
        if self.p.lane_changes and self.t >= self._next_lc_check:
            self._next_lc_check = self.t + 0.5
            self._lane_changes()
        gone = self.s - self.length > self.s_end[self.lane] if len(self.s) else np.zeros(0, bool)
        if gone.any():
            self._remove(~gone)

    def _lane_changes(self) -> None:
        lanes = self.layout.lanes
        gap, vl = self._leaders()
        a_cur = self._idm(self.v, self.v0, self.amax, self.bcomf, gap, vl)
        cand = np.nonzero((self.lc_until < self.t) & (self.rng.random(len(self.s)) < 0.25))[0]
        for i in cand:
            k = self.lane[i]
            for k2 in (k - 1, k + 1):
                if not 0 <= k2 < len(lanes) or lanes[k2].direction != lanes[k].direction:
                    continue
                others = np.nonzero(self.lane == k2)[0]
                ahead = others[self.s[others] > self.s[i]]
                behind = others[self.s[others] <= self.s[i]]
                g_new, v_lead = np.inf, 0.0
                if len(ahead):
                    j = ahead[np.argmin(self.s[ahead])]
                    g_new, v_lead = self.s[j] - self.length[j] - self.s[i], self.v[j]
                if g_new < S0 + 1.0:
                    continue
                a_new = self._idm(self.v[i : i + 1], self.v0[i : i + 1], self.amax[i : i + 1],
                                  self.bcomf[i : i + 1], np.array([g_new]), np.array([v_lead]))[0]
                if len(behind):
                    f = behind[np.argmax(self.s[behind])]
                    g_f = self.s[i] - self.length[i] - self.s[f]
                    if g_f < S0 + 1.0:
                        continue
                    a_f = self._idm(self.v[f : f + 1], self.v0[f : f + 1], self.amax[f : f + 1],
                                    self.bcomf[f : f + 1], np.array([g_f]), self.v[i : i + 1])[0]
                    if a_f < -2.5:
                        continue
                keep_right = 0.1 if lanes[k2].xc > lanes[k].xc and lanes[k].direction < 0 else 0.0
                if a_new - a_cur[i] + keep_right > 0.45:
                    self.lane[i] = k2
                    self.lc_until[i] = self.t + 6.0
                    break

    def warm_up(self, seconds: float, dt: float = 0.1) -> None:
        """Run the traffic before the scenario clock starts so the road is already populated at t = 0."""
        self.t = -float(seconds)
        self.next_arrival -= seconds
        self._next_lc_check = self.t
        while self.t < -1e-9:
            self.step(min(dt, -self.t))
        self.t = 0.0


def lane_at_x(layout: RoadLayout, x: np.ndarray) -> np.ndarray:
    """Lane ids (1-based) of lateral positions."""
    ids = np.array([ln.id for ln in layout.lanes], dtype=np.int64)
    return ids[layout.lane_index_at(x)] if len(x) else np.zeros(0, np.int64)
