"""Standing vehicles on loops seen in the image (appliance.presence), on flat textured vehicles rendered here.

The tracker's features are given by hand, so that a vehicle whose features are lost while it stands (what
happens to queued vehicles) can be set up exactly; the last test runs the whole pipeline and the measures.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from test_vision_pipeline import Scene, site_dict

from appliance.config import parse_site
from appliance.measures import TrafficMeasures
from appliance.pipeline import VisionPipeline
from appliance import presence
from appliance.background import Background
from appliance.presence import MOVE_OFF_S, STAND_S, STILL_LAG_S, LoopPresence
from appliance.types import Frame
from appliance.zones import SiteZones

FPS = 25.0
LOOP_Y = (30.0, 31.8)  # lane 1 (x -3.5 .. 0), approaching


class Road(Scene):
    """The test scenes' road with a verge of the road's grey around it instead of black: a frame's background
    darker than DAYLIGHT_GREY on average is dusk to the presence, where it asks nothing of the image."""

    def render(self, t: float, shake: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
        img = super().render(t, shake)
        M = np.array([[1, 0, shake[0]], [0, 1, shake[1]], [0, 0, 1]]) @ self.M
        inside = cv2.warpPerspective(np.ones_like(self.road), M, (img.shape[1], img.shape[0])) > 0
        return np.where(inside, img, np.uint8(110))


class StopScene(Road):
    """One dark car (lane 1) driving in at 8 m/s, braking at 2 m/s2 to stand with its front at y_stop from
    t_stop for stand_s, then driving off at 2 m/s2; a leader drives over the loop before it at 8 m/s, its rear
    leaving the loop 2.4 s before the car comes (the road under the loop is trusted once a vehicle has passed
    and left it as learnt: appliance.presence.TRUST_S)."""

    def __init__(self, y_stop: float = 29.0, t_stop: float = 8.0, stand_s: float = 60.0, others: int = 0,
                 leader: bool = True) -> None:
        """others: cars passing in lane 2 at 10 m/s, one every 4 s (a frame where nothing moves is skipped as
        a repeat, and the background is learnt from the frames that are not)."""
        super().__init__(seed=3)
        self.add_vehicle(-1.75, y_stop + 16.0 + 8.0 * (t_stop - 4.0), 4.5, -8.0)
        self.vehicles[0]["tex"] //= 3  # grey levels 0-84 on a road of 110: a textured grey car in the road's
        # grey would be as much like the road as it is unlike it
        for k in range(others):
            self.add_vehicle(1.75, 80.0 + 40.0 * k, 4.5, -10.0)
        self.y_stop, self.t_stop, self.stand_s = y_stop, t_stop, stand_s
        self.leader = leader
        if leader:  # 20 m ahead: over the loop (30-31.8 m) from t_stop - 4.85 s to t_stop - 4.1 s
            self.add_vehicle(-1.75, y_stop + 16.0 + 8.0 * (t_stop - 4.0) - 20.0, 4.5, -8.0)
            self.vehicles[-1]["tex"] //= 3

    def motion(self, t: float) -> tuple[float, float]:
        """Front y and speed (m/s, along -y) at t."""
        if t < self.t_stop - 4.0:
            return self.y_stop + 16.0 + 8.0 * (self.t_stop - 4.0 - t), 8.0
        if t < self.t_stop:
            dt = self.t_stop - t  # braking: the distance still to go is a dt^2 with a = 2 m/s2
            return self.y_stop + dt * dt, 2.0 * dt
        dt = max(t - self.t_stop - self.stand_s, 0.0)
        return self.y_stop - dt * dt, 2.0 * dt

    def positions(self, t: float) -> list[tuple[float, float]]:
        return [(-1.75, self.motion(t)[0])] + super().positions(t)[1:]


def make_site():
    d = site_dict()
    d["loops"] = [{"id": "L1", "lane": 1, "channel": 1, "y_m": LOOP_Y[0], "length_m": LOOP_Y[1] - LOOP_Y[0]}]
    return parse_site(d)


def features(scene: StopScene, t: float, lost_after: float | None) -> np.ndarray:
    """The car's features (x, y, vx, vy) as the tracker would hold them, none once lost_after has passed."""
    out = []
    if scene.leader:
        y = scene.positions(t)[-1][1]
        out += [[-2.0, y + 0.5, 0.0, -8.0], [-1.5, y + 3.0, 0.0, -8.0]]
    if lost_after is None or t <= lost_after:
        y, v = scene.motion(t)
        x, vy = -1.75, -v
        out += [[x - 0.5, y + 0.5, 0.0, vy], [x + 0.5, y + 2.0, 0.0, vy], [x, y + 4.0, 0.0, vy]]
    return np.array(out).reshape(-1, 4)


def passing() -> tuple[Scene, object]:
    """A dark car passing over the loop at 8 m/s (at 5 s), and its features."""
    scene = Road(seed=3)
    scene.add_vehicle(-1.75, 71.8, 4.5, -8.0)
    scene.vehicles[0]["tex"] //= 3

    def feats(t: float) -> np.ndarray:
        y = 71.8 - 8.0 * t
        return np.array([[-2.0, y + 0.5, 0.0, -8.0], [-1.5, y + 3.0, 0.0, -8.0]])

    return scene, feats


def watch(scene: Scene, seconds: float, feats, light=lambda t: 1.0, shake=lambda t: (0.0, 0.0), bg_light=None,
          stabilised: bool = False):
    """Run LoopPresence over the scene; the background it is given is the empty road under the same light (or bg_light(t): the background follows the light slowly); stabilised: the camera's
    shake is known (the stabiliser's offset), else it is taken for none."""
    site = make_site()
    pres = LoopPresence(site, SiteZones(site))
    empty = Road(seed=3).render(0.0)
    bg_light = bg_light or light
    out = []
    for k in range(int(seconds * FPS)):
        t = k / FPS
        img = np.clip(scene.render(t, shake(t)) * light(t), 0, 255).astype(np.uint8)
        bg = np.clip(empty * bg_light(t), 0, 255).astype(np.uint8)
        pres.step(t, img, bg, shake(t) if stabilised else (0.0, 0.0), feats(t))
        out.append((t, pres.sights["L1"].standing))
    return out


def spans(out) -> list[tuple[float, float, tuple]]:
    """(first, last time, the standing call's (came, stood)) of each run of standing calls."""
    runs: list = []
    for t, s in out:
        if s is not None and runs and runs[-1][1] >= t - 1.5 / FPS and runs[-1][2] == s:
            runs[-1][1] = t
        elif s is not None:
            runs.append([t, t, s])
    return [tuple(r) for r in runs]


def test_a_car_standing_on_a_loop_after_its_features_are_lost_holds_a_standing_call():
    """The car stops over the loop at 8 s; its features are lost 2 s later and it stands 60 s more. The call
    goes on when its patch has been still for STAND_S (still: unchanged over STILL_LAG_S), its on-time when it
    stood, stays on while it stands with no feature near (the road under the loop is not learnt meanwhile),
    and goes off as it drives off: MOVE_OFF_S after it moves at the latest, at once when the loop is free."""
    scene = StopScene(stand_s=60.0)
    out = watch(scene, 74.0, lambda t: features(scene, t, lost_after=10.0))
    runs = spans(out)
    assert len(runs) == 1, runs
    first, last, (came, stood) = runs[0]
    # its front came over the loop's far edge (31.8 m) at 6.3 s; crawling its last metre, its dark body (in
    # blocks of half a metre) shifts by a few pixels over the loop and looks still
    assert 6.3 <= came <= stood <= 8.1
    assert first == pytest.approx(stood + STILL_LAG_S + STAND_S, abs=0.1)
    assert 68.0 < last <= 68.0 + MOVE_OFF_S + 0.1


CASES = ["nobody came", "light", "cloud edge", "light while queued", "learnt with a car", "shake", "drift", "dusk"]


@pytest.mark.parametrize("case", CASES)
def test_no_standing_call_without_a_vehicle_standing(case, monkeypatch):
    """No call: a dark patch appearing on the loop 35 s after the last feature moved near it (a shadow of
    something beside the road creeping over it); the whole scene darkening by a third over 4 s (a cloud), or
    within 0.5 s with the background still showing the old light (a cloud's edge); the light dropping while
    something stands near the loop (the road is not learnt then) and the loop clearing after; the empty
    road learnt with a car standing on it (standing for MAX_STAND_S, here 15 s), which then drives off; the camera shaking
    by a pixel and a half, or drifting 12 px (the stabiliser knows it); a car standing at dusk, the road's grey
    at 77 (the road under a loop is lit by every headlight coming; the image is not asked then). Each case
    but the last two has a car driving over the loop first (at 5 s), so that the road is trusted."""
    scene, feats = passing()
    if case == "nobody came":
        scene.add_vehicle(-1.75, 29.0, 4.5, 0.0)  # there from the start, never moving, shown from 40 s
        original = scene.render
        before = passing()[0]
        scene.render = lambda t, sh=(0.0, 0.0): original(t, sh) if t >= 40.0 else before.render(t, sh)
        out = watch(scene, 60.0, feats)
    elif case == "light":
        out = watch(scene, 30.0, feats, light=lambda t: 1.0 - 0.33 * min(max(t - 10.0, 0.0) / 4.0, 1.0))
    elif case == "cloud edge":  # with cars passing in lane 2 over and over (features near the loop)
        near = np.array([[1.75, 31.0, 0.0, -8.0]])
        out = watch(scene, 20.0, lambda t: np.vstack([feats(t), near]),
                    light=lambda t: 1.0 - 0.45 * min(max(t - 10.0, 0.0) / 0.5, 1.0), bg_light=lambda t: 1.0)
    elif case == "light while queued":  # something stands beside the loop from 8 to 30 s (no features move)
        still = np.array([[-1.0, 36.0, 0.0, 0.0]])
        out = watch(scene, 45.0, lambda t: np.vstack([feats(t), still]) if 8.0 <= t < 30.0 else feats(t),
                    light=lambda t: 1.0 - 0.45 * min(max(t - 12.0, 0.0) / 4.0, 1.0))
    elif case == "learnt with a car":  # it stands from 8 s (its call from 9.5 s, learnt at 24.5 s) to 35 s
        monkeypatch.setattr(presence, "MAX_STAND_S", 15.0)
        scene = StopScene(stand_s=27.0)
        out = watch(scene, 55.0, lambda t: features(scene, t, 10.0) if t < 35.0 else features(scene, t, None))
        assert len(spans(out)) == 1 and spans(out)[0][1] < 25.0, spans(out)  # its own call, until learnt
        out = [(t, s) for t, s in out if t > 25.0]
    elif case == "shake":
        out = watch(scene, 30.0, feats, shake=lambda t: (1.5 * np.sin(7.0 * t), 1.5 * np.cos(5.0 * t)))
    elif case == "drift":
        out = watch(scene, 30.0, feats, shake=lambda t: (-12.0 * min(t / 20.0, 1.0), 12.0 * min(t / 20.0, 1.0)),
                    stabilised=True)
    else:
        scene = StopScene(stand_s=60.0)
        out = watch(scene, 30.0, lambda t: features(scene, t, 10.0), light=lambda t: 0.7)
    assert spans(out) == []


@pytest.mark.parametrize("standing_calls", [True, False])
def test_the_pipeline_and_the_measures_keep_a_standing_car_on_its_loop(standing_calls):
    """The whole path: a car stops over the loop for 40 s, then drives off. The loop gives one actuation for it
    (after its leader's), counted once, on from the car's arrival to its leaving within half a second, its call
    on all along, with the image's standing calls or without them (tracking.standing_calls = false): here the
    tracker keeps the standing car, and its footprint (only its front shows corners, so it is reported at a
    car's length) covers the loop. (Measured at the length of its front, 1-2 m, it used to leave the loop as it
    stopped; the standing call then held the loop.)"""
    d = site_dict()
    d["loops"] = [{"id": "L1", "lane": 1, "channel": 1, "y_m": LOOP_Y[0], "length_m": LOOP_Y[1] - LOOP_Y[0]}]
    d["tracking"] = {"standing_calls": standing_calls}
    site = parse_site(d)
    scene = StopScene(stand_s=40.0, t_stop=14.0, others=16)
    pipe = VisionPipeline(site)
    pipe.warmup()
    tm = TrafficMeasures(site)
    events, calls = [], []
    for k in range(int(60.0 * FPS)):
        t = k / FPS
        states = pipe.step(Frame(seq=k, t=t, wall=1767225600.0 + t, image=scene.render(t)))
        upd = tm.step(t, 1767225600.0 + t, states, pipe.loop_sights)
        events += upd.loop_events
        calls.append((t, tm.channels()[0].call))
    # the car's front reaches the loop's far edge (31.8 m) sqrt(2.8) s before it stops; its rear (4.5 m behind)
    # leaves the loop's near edge (30 m) sqrt(3.5) s after it drives off
    t_on, t_off = 14.0 - 2.8 ** 0.5, 54.0 + 3.5 ** 0.5
    assert len(events) == 2, events
    assert tm.channels()[0].count == 2
    assert events[0].t_off < 10.5  # the leader's, over the loop from 9.15 to 9.9 s
    assert events[1].t_on == pytest.approx(t_on, abs=0.5)
    assert events[1].t_off == pytest.approx(t_off, abs=0.5)
    assert all(c for t, c in calls if t_on + 0.5 < t < t_off - 0.5)


def test_a_reload_that_moves_only_the_loops_watches_them_where_they_are_now(tmp_path, shared_data):
    """The pipeline is kept (its tracks go on), but its loop patches follow the loops: the moved loop's patch
    is where the new config puts it, as a pipeline built for it would have it; the loop left as it was keeps
    its watch (what it learnt of the road under it)."""
    import tomllib

    import tomli_w
    from test_service_sitefiles import cdnet_site

    from appliance.config import load_site
    from appliance.service import Service, ServiceHooks

    cfg = cdnet_site(tmp_path, shared_data, frames=1)
    site = load_site(cfg)
    svc = Service(site, ServiceHooks(make_source=lambda s: None))
    svc.pipeline, svc.measures = VisionPipeline(site), TrafficMeasures(site)
    pipe = svc.pipeline
    d = tomllib.loads(cfg.read_text())
    d["loops"][0]["polygon_px"] = [[x, y - 30.0] for x, y in d["loops"][0]["polygon_px"]]
    cfg.write_text(tomli_w.dumps(d))
    new = load_site(cfg)
    before = [w.box for w in pipe.presence.watches]
    kept = pipe.presence.watches[1]
    svc._apply(new)
    assert svc.pipeline is pipe and pipe.presence.watches[1] is kept
    want = [w.box for w in VisionPipeline(new).presence.watches]
    assert [w.box for w in pipe.presence.watches] == want and want[0] != before[0] and want[1] == before[1]


@pytest.mark.parametrize("offset_known", [True, False])
def test_a_loops_road_is_first_taken_from_the_background_lined_up_with_the_frame(offset_known):
    """The background is learnt from the frames as they come, here with the camera at rest; the first frame the
    loop's watch sees is shaken 10 px right and 5 px up, which the stabiliser knows. Given the background lined
    up with that frame (the camera's offsets known to it), the empty road reads as the road; given it as learnt
    (the road 10 px away), as something on the loop, on a road striped like a crossing's markings."""
    site = make_site()
    pres = LoopPresence(site, SiteZones(site))
    empty = Road(seed=3).render(0.0)
    empty[:, ::7] = 200  # stripes 7 px apart, 2 px wide
    empty[:, 1::7] = 200
    bg = Background()
    while not bg.ready:
        bg.update(empty, (0.0, 0.0))
    shake = (10.0, -5.0)
    frame = cv2.warpAffine(empty, np.float32([[1, 0, shake[0]], [0, 1, shake[1]]]), empty.shape[::-1],
                           borderMode=cv2.BORDER_REPLICATE)
    bg.update(frame, shake if offset_known else (0.0, 0.0))
    pres.step(0.0, frame, bg.aligned, shake, np.zeros((0, 4)))
    share = pres.watches[0].share
    if offset_known:
        assert share < presence.EMPTY_SHARE
    else:
        assert share > presence.OCCUPIED_SHARE
