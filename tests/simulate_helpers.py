"""Helpers shared by the simulator tests: step a scene recording trajectories, find count-line crossings,
and compare a rendered vehicle's changed pixels with its projected box."""

from __future__ import annotations

import numpy as np
import pytest

from tools.simulate.scene import Scene
from tools.simulate.traffic import lane_at_x

# a scene with nothing but the vehicle placed by the test: no traffic, noise, gain, shadows or blur
CLEAN = dict(demand_vph=0.0, noise_sigma=0.0, auto_gain=False, shadows=False, motion_blur=False, defocus=0.0)
DT = 0.04

Snap = dict[int, tuple[float, int, float]]


def snap(sc: Scene) -> Snap:
    """Each live vehicle's front Y, lane id and length, keyed by vehicle id."""
    tr = sc.traffic
    lanes = lane_at_x(sc.layout, tr.x)
    return {int(i): (float(y), int(ln), float(L)) for i, y, ln, L in zip(tr.id, tr.y_front(), lanes, tr.length)}


def run_scene(preset: str, seed: int, seconds: float, period_s: float,
              **overrides: object) -> tuple[Scene, np.ndarray, list[Snap]]:
    """Step a scene (no rendering) by DT, recording every vehicle's front Y and lane at every step."""
    sc = Scene(preset, seed, period_s=period_s, **overrides)
    times, snaps = [0.0], [snap(sc)]
    for _ in range(int(round(seconds / DT))):
        sc.step(DT)
        times.append(sc.t)
        snaps.append(snap(sc))
    return sc, np.array(times), snaps


def crossings(times: np.ndarray, snaps: list[Snap], lane_id: int, y: float, direction: int) -> list[float]:
    """Times (interpolated between steps) at which vehicles in lane_id cross the line Y = y going direction."""
    out = []
    for k in range(1, len(snaps)):
        for vid, (y1, ln, _) in snaps[k].items():
            prev = snaps[k - 1].get(vid)
            if prev is None or ln != lane_id:
                continue
            y0 = prev[0]
            if (direction < 0 and y0 > y >= y1) or (direction > 0 and y0 < y <= y1):
                out.append(times[k - 1] + (y - y0) / (y1 - y0) * (times[k] - times[k - 1]))
    return out


def changed_pixels_match_box(img: np.ndarray, empty: np.ndarray, row: dict) -> tuple[np.ndarray, np.ndarray]:
    """Assert the pixels that differ from the empty scene span the row's projected box; returns their (xs, ys).

    The vehicle may be partly hidden by a sign or post drawn over it, and a face may match the road's grey
    at its edge, so the changed-pixel box must agree with the projected box within 2 px, not exactly."""
    ys, xs = np.nonzero(np.abs(img.astype(int) - empty.astype(int)) > 0)
    assert len(xs) > 50
    assert xs.min() == pytest.approx(row["bbox_x0"], abs=2.0)
    assert xs.max() == pytest.approx(row["bbox_x1"], abs=2.0)
    assert ys.min() == pytest.approx(row["bbox_y0"], abs=2.0)
    assert ys.max() == pytest.approx(row["bbox_y1"], abs=2.0)
    return xs, ys


def edie_totals(times: np.ndarray, snaps: list[Snap], lane_id: int, region: tuple[float, float], period_s: float,
                n_periods: int) -> tuple[np.ndarray, np.ndarray]:
    """Independent Edie totals per period: distance d(A) (m) and time t(A) (s) of the front points of lane_id's
    vehicles inside region [a0, a1], from the recorded steps sampled finely (10 sub-steps per step)."""
    a0, a1 = region
    dist, tim = np.zeros(n_periods), np.zeros(n_periods)
    sub = np.linspace(0.0, 1.0, 11)
    for k in range(1, len(snaps)):
        t0, t1 = times[k - 1], times[k]
        ids1 = np.fromiter(snaps[k].keys(), dtype=np.int64)
        ids0 = np.fromiter(snaps[k - 1].keys(), dtype=np.int64)
        common, i1, i0 = np.intersect1d(ids1, ids0, return_indices=True)
        if not len(common):
            continue
        v1 = np.array(list(snaps[k].values()))[i1]
        v0 = np.array(list(snaps[k - 1].values()))[i0]
        mine = v1[:, 1] == lane_id
        y0, y1 = v0[mine, 0], v1[mine, 0]
        ys = y0[:, None] + (y1 - y0)[:, None] * sub[None, :]
        ts = t0 + (t1 - t0) * sub
        mid_y, mid_t = 0.5 * (ys[:, 1:] + ys[:, :-1]), 0.5 * (ts[1:] + ts[:-1])
        inside = (mid_y >= a0) & (mid_y <= a1)
        step_d = np.abs(np.diff(ys, axis=1))
        for p in range(n_periods):
            sel = inside & ((mid_t >= p * period_s) & (mid_t < (p + 1) * period_s))[None, :]
            dist[p] += float(step_d[sel].sum())
            tim[p] += float(np.count_nonzero(sel) * (t1 - t0) / 10.0)
    return dist, tim


def assert_edie_rows(rows: list[dict], dist: np.ndarray, tim: np.ndarray, region: tuple[float, float],
                     seconds: float, period_s: float) -> None:
    """Each period row's q and k equal the independent totals over |A| = region length x covered time, q = k v."""
    a0, a1 = region
    for p, r in enumerate(rows):
        covered = min(period_s, seconds - p * period_s)
        area = (a1 - a0) / 1000.0 * covered / 3600.0
        # sub-sampling error is one sub-step per region crossing: < 0.5 % of totals over 30 s
        assert r["flow_vph"] == pytest.approx(dist[p] / 1000.0 / area, rel=5e-3)
        assert r["density_vpkm"] == pytest.approx(tim[p] / 3600.0 / area, rel=5e-3)
        assert r["flow_vph"] == pytest.approx(r["density_vpkm"] * r["speed_kmh"], rel=1e-9)
        assert r["partial"] == (covered < period_s)
