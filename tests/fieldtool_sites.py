"""Test material for the field tool tests: a site config dict and a store filled with traffic."""

from __future__ import annotations

import numpy as np

from appliance.store import Store
from appliance.types import LaneAggregate, LoopEvent, VehicleRecord

START = 1767225600.0  # 2026-01-01T00:00:00Z


def site_dict() -> dict:
    """A 2-lane approaching road, 640x480, calibration from an exact homography."""
    return {
        "site": {"name": "fieldtool-test"},
        "source": {"url": "synthetic:free-flow", "width": 640, "height": 480, "fps": 25.0},
        "calibration": {
            "image_px": [[200, 400], [440, 400], [280, 200], [360, 200]],
            "road_m": [[-3.5, 10.0], [3.5, 10.0], [-3.5, 50.0], [3.5, 50.0]],
        },
        "lanes": [
            {"id": 1, "direction": "approaching", "polygon_m": [[-3.5, 12], [0, 12], [0, 48], [-3.5, 48]],
             "detection_y_m": [40.0, 48.0], "exit_y_m": [12.0, 16.0]},
            {"id": 2, "direction": "approaching", "polygon_m": [[0, 12], [3.5, 12], [3.5, 48], [0, 48]]},
        ],
        "loops": [
            {"id": "L1", "lane": 1, "channel": 1, "y_m": 20.0, "length_m": 2.0},
            {"id": "L2", "lane": 2, "channel": 2, "y_m": 20.0},
        ],
        "fiducials": [[30.0, 30.0], [610.0, 40.0]],
    }


def newell_traffic(seconds: float, seed: int = 1, y0: float = 60.0, y1: float = 0.0, dt: float = 0.2):
    """Approaching vehicles (Y decreasing) in two lanes under Newell's car-following rule, with
    a slow-down of the first vehicle that sends a shock wave upstream. Yields, per lane, a list
    of (entry time s, times array, Y array, length m)."""
    rng = np.random.default_rng(seed)
    out = {}
    for lane in (1, 2):
        t = np.arange(0.0, seconds + 120.0, dt)
        # leader: 25 m/s, slows to 8 m/s between 60 and 90 s
        v = np.where((t > 60) & (t < 90), 8.0, 25.0)
        lead = y0 + 200.0 - np.cumsum(v) * dt  # starts 200 m upstream
        vehicles = []
        path = lead
        tau, d = 1.2 + 0.3 * lane, 7.0
        shift = 0.0
        while shift < seconds:
            lag = tau + rng.uniform(0.5, 4.0)
            shift += lag
            k = int(round(lag / dt))
            path = np.concatenate([np.full(k, path[0]), path[:-k]]) + d  # Newell: shifted in t and space
            inside = (path <= y0) & (path >= y1)
            if inside.sum() < 2:
                continue
            idx = np.flatnonzero(inside)
            vehicles.append((t[idx], path[idx], float(rng.choice([4.5, 4.5, 4.5, 9.0, 16.0]))))
        out[lane] = vehicles
    return out


def _length_class(length: float) -> str:
    return "small" if length < 6.1 else ("medium" if length < 13.1 else "large")


def fill_store(path, seconds: float = 1200.0, seed: int = 1, period_s: int = 300, trajectories: bool = True) -> dict:
    """Write vehicles, loop events and Edie period aggregates of ``newell_traffic`` into a real
    Store. Returns the written aggregates by (lane, period_start) for the tests to compare."""
    traffic = newell_traffic(seconds, seed)
    store = Store(path)
    region = (12.0, 48.0)
    L = region[1] - region[0]
    written = {}
    vid = 0
    for lane, vehicles in traffic.items():
        recs, events = [], []
        for t, y, length in vehicles:
            vid += 1
            if t[-1] > seconds:
                continue
            speed = float((y[0] - y[-1]) / (t[-1] - t[0]) * 3.6)
            recs.append(VehicleRecord(vid, lane, START + t[0], START + t[-1], speed, length,
                                      _length_class(length), 0,
                                      [(float(a), 0.0, float(b)) for a, b in zip(t, y)]))
            on = np.flatnonzero(y <= 21.8)
            if len(on):
                t_on = float(t[on[0]])
                v_here = 25.0 if not 60 < t_on < 200 else max(5.0, speed / 3.6)
                t_off = t_on + (1.8 + length) / v_here
                events.append(LoopEvent(f"L{lane}", lane, lane, t_on, t_off, START + t_on, START + t_off,
                                        v_here * 3.6, length, vid))
        store.write_vehicles(recs, trajectories=trajectories)
        store.write_loop_events(events)
        aggs = []
        for p0 in np.arange(0.0, seconds, period_s):
            dist = tim = 0.0
            count = 0
            speeds = []
            classes: dict[str, int] = {}
            for t, y, length in vehicles:
                m = (t >= p0) & (t < p0 + period_s) & (y >= region[0]) & (y <= region[1])
                if m.sum() >= 2:
                    dist += float(y[m].max() - y[m].min())
                    tim += float(t[m][-1] - t[m][0])
                c = np.flatnonzero((y[:-1] > 30.0) & (y[1:] <= 30.0))
                if len(c) and p0 <= t[c[0]] < p0 + period_s:
                    count += 1
                    cls = _length_class(length)
                    classes[cls] = classes.get(cls, 0) + 1
                    speeds.append(float((y[c[0]] - y[c[0] + 1]) / (t[c[0] + 1] - t[c[0]]) * 3.6))
            area = L * period_s
            occ = sum(e.t_off - e.t_on for e in events if p0 <= e.t_on < p0 + period_s) / period_s * 100
            a = LaneAggregate(
                lane=lane, period_start=START + p0, period_s=float(period_s), count=count,
                flow_vph=dist / area * 3600.0, density_vpkm=tim / area * 1000.0,
                speed_kmh=dist / tim * 3.6 if tim else None,
                time_mean_speed_kmh=float(np.mean(speeds)) if speeds else None,
                occupancy_pct=occ, speed85_kmh=float(np.percentile(speeds, 85)) if speeds else None,
                headway_s=period_s / count if count else None, class_counts=classes,
                partial=p0 == 0.0, quality=0)
            aggs.append(a)
            written[(lane, START + p0)] = a
        store.write_periods(aggs, written_wall=START + seconds)
    store.write_health(START + 400.0, "CAMERA_LOST", True, "rtsp timeout")
    store.write_health(START + 412.0, "CAMERA_LOST", False, "reconnected")
    store.close()
    return written
