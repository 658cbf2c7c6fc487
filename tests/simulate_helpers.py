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
