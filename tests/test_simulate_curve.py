"""Curved road: geometry, rendered markings and vehicles, site config and exact truth all follow the bend."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import tomllib

import numpy as np
import pytest

from appliance.config import load_site, parse_site
from appliance.geometry import polygon_contains
from simulate_helpers import CLEAN, DT, assert_edie_rows, changed_pixels_match_box, crossings, edie_totals, run_scene
from tools.simulate.scene import Scene
from tools.simulate.stream import site_toml

R = -350.0  # the `curve` preset's radius
SECONDS = 60.0
PERIOD = 30.0


def _bend(y) -> np.ndarray:
    """The bend as documented (tools.simulate.road): X shift Y^2 / 2R, a parabola with curvature 1/R at the
    camera that straightens slowly with distance (so Y stays monotonic along every lane); slope Y / R."""
    y = np.asarray(y, dtype=np.float64)
    return y * y / (2.0 * R)


def _site(sc: Scene):
    return parse_site(tomllib.loads(site_toml(sc.site_dict("video.mp4"))))


def test_site_config_lanes_follow_the_curve_and_loops_lie_inside() -> None:
    sc = Scene("curve", 1)
    cfg = _site(sc)  # validated by appliance.config, the service's own reader
    for lane, ln in zip(cfg.lanes, sc.layout.lanes):
        poly = np.asarray(lane.polygon_m)
        assert len(poly) >= 20
        left, right = poly[: len(poly) // 2], poly[len(poly) // 2:]
        # vertices on the lane edges: straight-road edge plus the bend (coordinates are written to 1 mm)
        assert np.allclose(left[:, 0], ln.x0 + _bend(left[:, 1]), atol=2e-3)
        assert np.allclose(right[:, 0], ln.x1 + _bend(right[:, 1]), atol=2e-3)
        # the bend is real: the far end of the lane is shifted by metres, not centimetres
        assert abs(_bend(poly[:, 1].max())) > 5.0
        lane_y = poly[:, 1]
        assert lane.region_y_m[0] >= lane_y.min() and lane.region_y_m[1] <= lane_y.max()
    for lp in cfg.loops:
        loop = np.asarray(lp.polygon_m)
        lane_poly = np.asarray(cfg.lane(lp.lane).polygon_m)
        assert polygon_contains(lane_poly, loop.mean(axis=0, keepdims=True))[0]
        # the clipped loop's corners sit on the curved lane edges at its two Y ends
        ln = sc.layout.lanes[lp.lane - 1]
        assert np.allclose(np.sort(loop[:, 1])[[0, -1]], [lp.y_m, lp.y_m + lp.length_m], atol=1e-6)
        # (a 5 m chord of the polygon deviates from the parabola by at most 5^2 / 8|R| < 1 cm)
        assert (loop[:, 0] >= ln.x0 + _bend(loop[:, 1]) - 0.01).all()
        assert (loop[:, 0] <= ln.x1 + _bend(loop[:, 1]) + 0.01).all()


def test_markings_are_painted_along_the_curve() -> None:
    sc = Scene("curve", 2, **CLEAN)
    img, _ = sc.render()
    ys = np.arange(12.0, 70.0, 1.0)
    x_edge = sc.layout.x_min + 0.1  # left edge line, 0.2 m wide
    line = sc.cam.road_to_image(np.column_stack([x_edge + _bend(ys), ys]))
    asphalt = sc.cam.road_to_image(np.column_stack([x_edge + 1.2 + _bend(ys), ys]))
    # had the line been painted straight, it would be 0.2 .. 7 m away from where the bend puts it
    straight = sc.cam.road_to_image(np.column_stack([np.full_like(ys, x_edge), ys]))

    def grey(px: np.ndarray) -> np.ndarray:
        u, v = np.round(px).astype(int).T
        ok = (u >= 0) & (u < img.shape[1]) & (v >= 0) & (v < img.shape[0])
        return img[v[ok], u[ok]].astype(float)

    # paint (about 205 before exposure) against asphalt (about 100): the sampled line must be clearly brighter
    on_line, road = grey(line), grey(asphalt)
    assert len(on_line) > 30
    assert np.median(on_line) > np.median(road) + 40
    far = ys > 40  # beyond 40 m the straight position is more than 2 m off the curved line
    assert np.median(grey(straight[far])) < np.median(on_line) - 40


@pytest.mark.parametrize("lane_idx, cls, y_front", [(0, "car", 40.0), (1, "truck", 70.0), (2, "bus", 45.0)])
def test_projected_box_matches_rendered_pixels_on_the_curve(lane_idx: int, cls: str, y_front: float) -> None:
    sc = Scene("curve", 4, lane_changes=False, class_mix={cls: 1.0}, **CLEAN)
    empty, rows = sc.render()
    assert rows == []
    tr = sc.traffic
    assert tr._spawn(lane_idx)
    ln = sc.layout.lanes[lane_idx]
    tr.s[0] = ln.s_of(y_front)
    img, rows = sc.render()
    assert len(rows) == 1
    r = rows[0]
    xs, ys = changed_pixels_match_box(img, empty, r)
    assert r["visible_frac"] > 0.8
    # truth in road X/Y: the front centre sits on the bent lane; the body lies along the tangent there
    heading = math.atan(y_front / R)  # dX/dY of the bend is Y/R
    assert r["y_front_m"] == pytest.approx(y_front)
    assert r["x_m"] == pytest.approx(tr.x[0] + _bend(y_front), abs=1e-9)
    assert r["y_rear_m"] == pytest.approx(y_front - ln.direction * r["length_m"] * math.cos(heading), abs=1e-9)
    # the rendered vehicle is inside its lane as the site config draws it: centre of the changed pixels
    cfg = _site(sc)
    centre_road = sc.cam.image_to_road(np.array([[xs.mean(), ys.max()]]))  # lowest pixel: on the road plane
    lane_poly = np.asarray(cfg.lane(ln.id).polygon_m)
    widened = lane_poly.copy()
    widened[: len(widened) // 2, 0] -= 1.0  # the lowest pixel may be a bottom corner: allow 1 m sideways
    widened[len(widened) // 2:, 0] += 1.0
    assert polygon_contains(widened, centre_road)[0], centre_road


@pytest.fixture(scope="module")
def curved():
    # no lane changes, so loop and count-line tallies must agree exactly
    return run_scene("curve", 5, SECONDS, PERIOD, lane_changes=False, demand_vph=1300.0)


def test_curve_counts_equal_trajectories_and_loop_actuations(curved) -> None:
    sc, times, snaps = curved
    for ln in sc.truth.lanes:
        mine = sorted(crossings(times, snaps, ln.id, ln.count_y, ln.direction))
        theirs = sorted(c[2] for c in sc.truth.crossings if c[0] == ln.id)
        assert len(mine) == len(theirs) > 5
        assert np.allclose(mine, theirs, atol=1e-6)
        crossing_ids = {c[1] for c in sc.truth.crossings if c[0] == ln.id}
        loop_ids = {e["vehicle_id"] for e in sc.truth.loop_events if e["lane"] == ln.id}
        # the loop is centred on the count line: only a vehicle still on the loop at the end may differ
        assert len(crossing_ids ^ loop_ids) <= 1, (len(crossing_ids), len(loop_ids))


def test_curve_loop_on_off_match_the_turned_body(curved) -> None:
    sc, times, snaps = curved
    loops = {lp.id: lp for lp in sc.truth.loops}
    lanes = {ln.id: ln for ln in sc.truth.lanes}
    events = sc.truth.loop_events
    assert len(events) > 20
    turn_effect = []
    for e in events[:40]:
        lp, ln = loops[e["loop_id"]], lanes[e["lane"]]
        track = [(t, s[e["vehicle_id"]][0]) for t, s in zip(times, snaps) if e["vehicle_id"] in s]
        ts, ys = np.array(track).T
        y_on = float(np.interp(e["t_on"], ts, ys))
        y_off = float(np.interp(e["t_off"], ts, ys))
        # on the bend a body of length L covers L cos(heading) of Y; heading from the bend's slope Y/R
        span_off = e["length_m"] * math.cos(math.atan(y_off / R))
        if ln.direction < 0:  # front reaches the far edge, rear leaves the near edge
            assert y_on == pytest.approx(lp.y0 + lp.length, abs=1e-4)  # times are written to 1 us
            # t_off is interpolated within a 40 ms step in which cos(heading) changes by < 1e-4: < 1 mm
            assert y_off + span_off == pytest.approx(lp.y0, abs=1e-3)
        else:
            assert y_on == pytest.approx(lp.y0, abs=1e-4)
            assert y_off - span_off == pytest.approx(lp.y0 + lp.length, abs=1e-3)
        turn_effect.append(e["length_m"] - span_off)
    # the turn matters at the loops: ignoring it would be off by far more than the 1 mm tolerance
    assert max(turn_effect) > 1e-2 and np.median(turn_effect) > 3e-3


def test_curve_edie_matches_trajectories_and_q_equals_kv(curved) -> None:
    sc, times, snaps = curved
    aggs = sc.truth.aggregates()
    n_periods = int(math.ceil(SECONDS / PERIOD))
    assert len(aggs) == len(sc.truth.lanes) * n_periods
    for ln in sc.truth.lanes:
        dist, tim = edie_totals(times, snaps, ln.id, ln.region, PERIOD, n_periods)
        rows = [r for r in aggs if r["lane"] == ln.id]
        assert_edie_rows(rows, dist, tim, ln.region, SECONDS, PERIOD)
        assert all(r["flow_vph"] > 0 for r in rows)


def test_huge_radius_gives_the_straight_scene() -> None:
    """The curved code path with a negligible bend (2 um at 60 m) reproduces the straight scene's truth."""
    def run(**kw):
        sc = Scene("demo", 7, **kw)
        out = []
        for _ in range(10):
            sc.step(DT)
            out.append(sc.render()[1])
        return sc, out

    straight, rows_s = run()
    bent, rows_b = run(curve_radius_m=1e9)
    assert bent.layout.curved and not straight.layout.curved
    assert sum(len(r) for r in rows_s) > 10
    for a, b in zip(rows_s, rows_b):
        assert [r["vehicle_id"] for r in a] == [r["vehicle_id"] for r in b]
        for ra, rb in zip(a, b):
            for k in ("x_m", "y_front_m", "y_rear_m", "bbox_x0", "bbox_y0", "bbox_x1", "bbox_y1"):
                assert rb[k] == pytest.approx(ra[k], abs=1e-3), k
    assert straight.truth.crossings == bent.truth.crossings
    sa, sb = straight.site_dict("v"), bent.site_dict("v")
    for la, lb in zip(sa["lanes"], sb["lanes"]):
        assert la["region_y_m"] == lb["region_y_m"] and la["count_y_m"] == lb["count_y_m"]
        pa, pb = np.asarray(la["polygon_m"]), np.asarray(lb["polygon_m"])
        assert pa[:, 0].min() == pytest.approx(pb[:, 0].min(), abs=1e-3)
        assert pa[:, 1].max() == pytest.approx(pb[:, 1].max(), abs=1e-3)


def test_too_tight_a_curve_is_refused() -> None:
    with pytest.raises(ValueError, match="too tight"):
        Scene("free-flow", 1, curve_radius_m=80.0)


@pytest.mark.parametrize("overrides", [dict(night=True, shadows=False), dict(rain=True, overcast=True, shadows=False)])
def test_curve_renders_at_night_and_in_rain(overrides: dict) -> None:
    sc = Scene("curve", 3, **overrides)
    for _ in range(3):
        sc.step(DT)
    img, rows = sc.render()
    assert rows and img.shape == (480, 640)
    assert all(r["bbox_x1"] > r["bbox_x0"] for r in rows)


def test_cli_curve_radius_writes_a_loadable_site(tmp_path) -> None:
    out = tmp_path / "bend"
    r = subprocess.run([sys.executable, "-m", "tools.cli", "simulate", "--preset", "free-flow", "--curve-radius", "500",
                        "--seconds", "1", "--out", str(out), "--quiet"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    cfg = load_site(out / "site.toml")
    poly = np.asarray(cfg.lanes[0].polygon_m)
    assert len(poly) >= 20 and poly[:, 0].max() - poly[:, 0].min() > 5.0  # bends right by metres
    assert json.loads((out / "truth" / "meta.json").read_text())["road"]["curve_radius_m"] == 500.0
    bad = subprocess.run([sys.executable, "-m", "tools.cli", "simulate", "--curve-radius", "50", "--seconds", "1",
                          "--out", str(tmp_path / "bad"), "--quiet"], capture_output=True, text=True, timeout=300)
    assert bad.returncode != 0 and "too tight" in bad.stderr
