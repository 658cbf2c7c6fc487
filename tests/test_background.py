"""The road background model and its image tests: a shadow darkens the road by one factor and keeps its
texture, a vehicle (dark or bright) hides it; two parts are one body where no road shows between them."""

import numpy as np
import pytest

from appliance import background
from appliance.background import (FAST_STEP, FAST_UPDATES, SETTLE_UPDATES, UPDATE_EVERY, WARMUP_EVERY,
                                  WARMUP_SAMPLES, Background, temporal_median)


def _road(seed: int = 0, std: float = 14.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    road = 120 + rng.normal(0, std, (120, 160))
    return np.clip(road, 0, 255).astype(np.uint8)


def _learnt(road: np.ndarray, noise_seed: int = 1) -> Background:
    bg = Background()
    rng = np.random.default_rng(noise_seed)
    for _ in range(WARMUP_SAMPLES * WARMUP_EVERY + 5 * UPDATE_EVERY):
        bg.update(np.clip(road + rng.normal(0, 2, road.shape), 0, 255).astype(np.uint8))
    return bg


def _following(road: np.ndarray) -> Background:
    """A background learnt from road and past its first fast updates: it follows the frames a step at a time."""
    bg = _learnt(road)
    while bg.updates < FAST_UPDATES:
        bg.update(road)
    return bg


def _box_scene() -> tuple[np.ndarray, Background, np.ndarray]:
    """A textured road, its learnt background, and four points whose test box is rows 37-73, columns 47-103."""
    road = _road()
    return road, _learnt(road), np.array([[50.0, 40.0], [100.0, 40.0], [50.0, 70.0], [100.0, 70.0]])


def test_background_learns_the_empty_road_through_passing_vehicles():
    road = _road()
    bg = Background()
    first = road.copy()
    first[30:70, 40:90] = 230  # a vehicle stands in the first frame
    bg.update(first)
    for i in range((WARMUP_SAMPLES - 1) * WARMUP_EVERY):
        assert not bg.ready  # nothing learnt yet: the image tests answer "no"
        img = road.copy()
        x = (i * 7) % 140
        img[80:100, x:x + 20] = 20  # vehicles pass, each pixel covered a short while
        bg.update(img)
    assert bg.ready and not bg.settled  # the loops' watches wait for the running median to follow on
    err = np.abs(bg.bg.astype(int) - road.astype(int))
    assert np.median(err) <= 2 and np.percentile(err, 99) <= 12, (np.median(err), np.percentile(err, 99))


def test_a_vehicle_standing_through_the_start_is_unlearnt_before_the_background_settles():
    """A bright truck stands in the same place through the start: the start's median holds it. By the time the
    background has settled (the loops' watches start from it then), the road it left is learnt again."""
    road = _road()
    truck = road.copy()
    truck[30:70, 40:90] = 230
    bg = Background()
    while not bg.ready:
        bg.update(truck)
    assert np.abs(bg.bg[30:70, 40:90].astype(int) - road[30:70, 40:90]).min() > 50  # the median holds it
    while not bg.settled:
        bg.update(road)
    err = np.abs(bg.bg.astype(int) - road.astype(int))
    assert err.max() < FAST_STEP, err.max()  # within a step of it
    assert bg.updates == SETTLE_UPDATES


@pytest.mark.parametrize("selective", [True, False])
def test_traffic_covering_a_place_most_of_the_time_does_not_drag_the_background_off_the_road(monkeypatch,
                                                                                            selective):
    """Far away, tall vehicles and their shadows cover some rows most of the time: here a dark platoon covers a
    patch for 2 s in every 3 (25 fps). Learning what it sees there at every update, the running median follows
    the vehicles down; learning such far-off pixels at one update in FOREGROUND_EVERY, it stays on the road."""
    if not selective:
        monkeypatch.setattr(background, "FOREGROUND_EVERY", 1)
    road = _road()
    bg = _following(road)
    for i in range(25 * 60):
        img = road.copy()
        if i % 75 < 50:
            img[30:70, 40:90] = 40
        bg.update(img)
    err = np.abs(bg.bg[30:70, 40:90].astype(int) - road[30:70, 40:90].astype(int))
    if selective:
        assert np.percentile(err, 90) <= 6, np.percentile(err, 90)
    else:
        assert np.median(err) > 20  # what the test guards against


@pytest.mark.parametrize("light_rule", [True, False])
def test_when_the_light_changes_the_whole_background_follows_at_once(monkeypatch, light_rule):
    """The camera's gain rises: the whole frame is 40 grey levels brighter. Everything is that far off the
    background, which is the light's doing, not traffic's: it is learnt at every update (without the rule, at
    one in FOREGROUND_EVERY, it lags by tens of levels)."""
    if not light_rule:
        monkeypatch.setattr(background, "LIGHT_CHANGE_SHARE", 1.0)
    road = _road()
    bg = _following(road)
    bright = np.clip(road.astype(int) + 40, 0, 255).astype(np.uint8)
    for _ in range(45 * UPDATE_EVERY):
        bg.update(bright)
    err = np.abs(bg.bg.astype(int) - bright.astype(int))
    if light_rule:
        assert np.median(err) <= 1, np.median(err)
    else:
        assert np.median(err) > 20


def test_the_background_lines_up_with_the_camera_it_learnt_from():
    """Frames taken shaking about (4, -2) px: the start's median lines up there; the camera then drifts 20 px
    in 20 s (25 fps), and the background follows it within a pixel."""
    road = _road()
    bg = Background()
    k = 0
    while not bg.ready:
        bg.update(road, (4.0 + 3.0 * np.sin(k), -2.0 + 3.0 * np.cos(1.3 * k)))
        k += 1
    np.testing.assert_allclose(bg.offset, (4.0, -2.0), atol=1.0)
    for i in range(500):
        bg.update(road, (4.0 + 20.0 * i / 499.0, -2.0))
    np.testing.assert_allclose(bg.offset, (24.0, -2.0), atol=1.0)


@pytest.mark.parametrize("n", [25, 8])
def test_temporal_median_matches_numpy(n):
    stack = np.random.default_rng(n).integers(0, 256, (n, 30, 40)).astype(np.uint8)
    out = np.empty((30, 40), np.uint8)
    temporal_median(stack, out)
    expect = np.median(stack, axis=0) if n % 2 else np.sort(stack, axis=0)[n // 2]
    np.testing.assert_array_equal(out, expect)


@pytest.mark.parametrize("offset_known", [True, False])
def test_the_image_tests_compare_a_shaken_frame_with_the_road_where_it_lies(offset_known):
    """The road learnt with the camera at rest; a frame shaken 5 px right and 3 px down shows a shadow. With the
    frame's offset known, the shadow test compares it with the road under it and finds the shadow; compared
    pixel by pixel with the road 5 px away, it does not."""
    road, bg, pts = _box_scene()
    shadow = road.copy()
    shadow[40:71, 50:101] = (road[40:71, 50:101] * 0.5).astype(np.uint8)
    frame = np.roll(shadow, (3, 5), axis=(0, 1))
    bg.update(frame, (5.0, 3.0) if offset_known else (0.0, 0.0))
    assert bg.is_shadow(frame, pts + [5.0, 3.0]) == offset_known


def test_shadow_is_told_from_dark_and_bright_vehicles():
    road, bg, pts = _box_scene()
    shadow = road.copy()
    shadow[40:71, 50:101] = (road[40:71, 50:101] * 0.5).astype(np.uint8)
    assert bg.is_shadow(shadow, pts)
    dark_car = road.copy()
    paint = np.random.default_rng(5).normal(55, 12, (31, 51))  # as dark as the shadow, its own texture
    dark_car[40:71, 50:101] = np.clip(paint, 0, 255).astype(np.uint8)
    assert not bg.is_shadow(dark_car, pts)
    flat_car = road.copy()
    flat_car[40:71, 50:101] = 55  # uniformly dark: no texture at all
    assert not bg.is_shadow(flat_car, pts)
    beside = road.copy()  # a plain grey car and its own shadow beside it, half the box each
    beside[40:71, 50:75] = np.clip(62 + np.random.default_rng(3).normal(0, 3, (31, 25)), 0, 255).astype(np.uint8)
    beside[40:71, 75:101] = (road[40:71, 75:101] * 0.5).astype(np.uint8)
    assert not bg.is_shadow(beside, pts)  # over the whole box the shadow's half correlates with the road
    bright_car = shadow.copy()
    bright_car[45:60, 60:90] = 220  # a vehicle standing in the shadow
    assert not bg.is_shadow(bright_car, pts)
    assert not bg.is_shadow(road, pts)  # nothing there
    assert not Background().is_shadow(shadow, pts)  # no background learnt yet: no answer


def test_on_a_plain_road_an_even_dimming_counts_only_where_allowed():
    """Where the road has no texture to see through a shadow, an evenly dimmed box may be a shadow (with its
    caster beside it, the grouper's attached test) but is no proof of one on its own (plain_ok=False)."""
    road = np.full((120, 160), 120, np.uint8)
    bg = _learnt(road)
    pts = np.array([[50.0, 40.0], [100.0, 40.0], [50.0, 70.0], [100.0, 70.0]])
    dimmed = road.copy()
    dimmed[40:71, 50:101] = 60
    assert bg.is_shadow(dimmed, pts)
    assert not bg.is_shadow(dimmed, pts, plain_ok=False)


def test_two_parts_are_one_body_only_where_the_image_between_them_is_off_the_road():
    road = _road()
    bg = _learnt(road)
    cab = np.array([[60.0, 90.0], [75.0, 92.0]])  # a truck's cab, low in the image
    top = np.array([[40.0, 30.0], [52.0, 34.0]])  # its box's top, higher and off to one side
    truck = road.copy()
    truck[28:95, 38:80] = np.clip(180 + np.random.default_rng(7).normal(0, 6, (67, 42)), 0, 255).astype(np.uint8)
    assert bg.is_joined(truck, top, cab)
    two = road.copy()  # two vehicles, with the road between them
    two[80:95, 58:80] = 200
    two[28:40, 38:56] = 60
    assert not bg.is_joined(two, top, cab)
    assert not Background().is_joined(truck, top, cab)  # no road learnt yet: no answer but "no"


@pytest.mark.parametrize("bright_share, shadow", [(0.05, True), (0.12, False)])
def test_a_shadow_may_hold_a_little_of_its_bright_caster_but_not_more(bright_share, shadow):
    """MAX_BRIGHT_SHARE (8 %): a shadow's box may take in a sliver of the bright vehicle casting it; a box with
    more of it brightened is a vehicle there."""
    road, bg, pts = _box_scene()
    img = road.copy()
    img[37:74, 47:104] = (road[37:74, 47:104] * 0.5).astype(np.uint8)  # the whole box (points + 3 px) shadowed
    cols = int(round(bright_share * 57))  # full-height strips at the box's left edge: the caster's side
    img[37:74, 47:47 + cols] = 235
    assert bg.is_shadow(img, pts) == shadow


@pytest.mark.parametrize("second_share, shadow", [(0.3, True), (0.5, False)])
def test_a_shadow_dims_the_road_by_one_factor(second_share, shadow):
    """MIN_CORE_SHARE (65 %): a shadow dims the road it covers by one factor (the sky's share of light); a box
    dimmed half by 0.5 and half by 0.72 (a dark vehicle's paint over the road's texture would spread the ratios
    as much) is no shadow, one with 30 % of its dark pixels off the main factor still is (penumbra, edges)."""
    road, bg, pts = _box_scene()
    img = road.copy()
    split = 47 + int(round((1.0 - second_share) * 57))
    img[37:74, 47:split] = (road[37:74, 47:split] * 0.5).astype(np.uint8)
    img[37:74, split:104] = (road[37:74, split:104] * 0.72).astype(np.uint8)
    assert bg.is_shadow(img, pts) == shadow


@pytest.mark.parametrize("road_share, joined", [(0.08, True), (0.3, False)])
def test_two_parts_are_one_body_unless_road_shows_on_the_line_between_them(road_share, joined):
    """MIN_JOINED_SHARE (85 %): the line between a tall vehicle's parts may cross a little road-coloured image
    (a window, a shadowed gap); with more road on it the two are separate vehicles."""
    road = _road()
    bg = _learnt(road)
    a, b = np.array([[40.0, 60.0]]), np.array([[140.0, 60.0]])
    img = road.copy()
    img[50:71, 38:143] = np.clip(200 + np.random.default_rng(8).normal(0, 5, (21, 105)), 0, 255).astype(np.uint8)
    gap = int(round(road_share * 101))  # of the line's 101 pixels
    img[50:71, 90:90 + gap] = road[50:71, 90:90 + gap]
    assert bg.is_joined(img, a, b) == joined


@pytest.mark.parametrize("dark_share, attached", [(0.7, True), (0.5, False)])
def test_a_shadow_belongs_to_a_caster_only_where_the_road_between_them_is_shadowed_too(dark_share, attached):
    """MIN_ATTACHED_DARK (60 %): a shadow touches its caster, so the road between the two (across the rows
    they share) is dark too, up to a sunlit sliver where the caster's outline and the features' places do not
    meet; a vehicle with sunlit road between it and the shadow is not the one casting it."""
    road = _road()
    bg = _learnt(road)
    pts = np.array([[50.0, 40.0], [80.0, 40.0], [50.0, 70.0], [80.0, 70.0]])  # on the shadow
    caster = np.array([[120.0, 42.0], [140.0, 42.0], [120.0, 68.0], [140.0, 68.0]])
    img = road.copy()
    img[37:74, 47:84] = (road[37:74, 47:84] * 0.5).astype(np.uint8)
    img[38:73, 118:143] = np.clip(200 + np.random.default_rng(9).normal(0, 5, (35, 25)), 0, 255).astype(np.uint8)
    # the gap between them, columns 80-119: shadowed from the shadow's side for dark_share of its width
    dark_to = 80 + int(round(dark_share * 40))
    img[37:74, 84:dark_to] = (road[37:74, 84:dark_to] * 0.5).astype(np.uint8)
    assert bg.is_shadow(img, pts)
    assert bg.is_attached_shadow(img, pts, caster) == attached


@pytest.mark.parametrize("factor, shadow", [(0.12, False), (0.3, True), (0.8, True), (0.9, False)])
def test_a_shadow_keeps_some_of_the_light_and_takes_some_away(factor, shadow):
    """SHADOW_RATIO (0.2-0.85): the sky still lights a shadowed road (a box dimmed to 12 % is a black vehicle,
    not a shadow), and a shadow takes a good share of the sun's light away (dimmed to 90 % is the road under a
    passing cloud or the camera's gain, which the grouper must not take for a vehicle's shadow)."""
    road, bg, pts = _box_scene()
    img = road.copy()
    img[37:74, 47:104] = (road[37:74, 47:104] * factor).astype(np.uint8)
    assert bg.is_shadow(img, pts) == shadow


@pytest.mark.parametrize("dark_share, shadow", [(0.1, False), (0.25, True)])
def test_a_shadow_darkens_a_share_of_its_box(dark_share, shadow):
    """MIN_DARK_SHARE (15 %): features on a shadow's edge take in sunlit road around them; a box with only a
    sliver darkened holds no shadow to speak of."""
    road, bg, pts = _box_scene()
    img = road.copy()
    cols = int(round(dark_share * 57))
    img[37:74, 47:47 + cols] = (road[37:74, 47:47 + cols] * 0.5).astype(np.uint8)
    assert bg.is_shadow(img, pts) == shadow


@pytest.mark.parametrize("own, shadow", [(0.5, True), (0.85, False)])
def test_the_road_must_show_through_a_shadow(own, shadow):
    """MIN_TEXTURE_NCC (0.5): in a shadow the road's own texture correlates with the learnt road's; a dark area
    whose pattern is mostly its own (share own of its variance from a texture of its own: a vehicle's paint,
    dirt, a rough shadowed body) is no shadow, though its grey level and spread match the shadowed road's."""
    road, bg, pts = _box_scene()
    texture = np.random.default_rng(21).normal(0, 14, road.shape)
    mixed = 120 + np.sqrt(1.0 - own) * (road.astype(float) - 120) + np.sqrt(own) * texture
    img = road.copy()
    img[37:74, 47:104] = np.clip(0.5 * mixed[37:74, 47:104], 0, 255).astype(np.uint8)
    assert bg.is_shadow(img, pts) == shadow


@pytest.mark.parametrize("road_share, shadow", [(0.75, True), (0.45, False)])
def test_most_of_a_shadow_shows_the_road_through_it(road_share, shadow):
    """MIN_CELL_SHARE (60 %): the box is judged in cells, most of which must show the road's texture through
    the shadow (a few may not: a stain, a dark patch of paint at the caster's edge); a dark area with the road
    showing in less than half of it is a vehicle beside its own shadow."""
    road, bg, pts = _box_scene()
    texture = 120 + np.random.default_rng(22).normal(0, 14, road.shape)
    img = road.copy()
    split = 47 + int(round(road_share * 57 / 6)) * 6
    img[37:74, 47:split] = (road[37:74, 47:split] * 0.5).astype(np.uint8)
    img[37:74, split:104] = np.clip(texture[37:74, split:104] * 0.5, 0, 255).astype(np.uint8)
    assert bg.is_shadow(img, pts) == shadow


@pytest.mark.parametrize("second, shadow", [(0.58, True), (0.645, False)])
def test_a_shadows_core_is_one_factor_within_a_tolerance(second, shadow):
    """CORE_TOL (0.1): the dark pixels within this of the median ratio are the shadow's core. A box dimmed to
    0.5 over 60 % of it and to 0.58 over the rest (a shadow's uneven edge, the road's own shading) is one
    shadow; dimmed by two factors further apart (0.5 and 0.645: as far apart as a dark vehicle's paint spreads
    the ratios over the road) only 60 % of the box, less than MIN_CORE_SHARE, is core. (The median ratio reads
    0.52: the road's learnt noise spreads the first part.)"""
    road, bg, pts = _box_scene()
    img = road.copy()
    split = 47 + int(round(0.6 * 57))
    img[37:74, 47:split] = np.round(road[37:74, 47:split] * 0.5).astype(np.uint8)
    img[37:74, split:104] = np.round(road[37:74, split:104] * second).astype(np.uint8)
    assert bg.is_shadow(img, pts) == shadow


def _small_box(texture_std: float) -> tuple[np.ndarray, Background, np.ndarray]:
    """A road of this texture, its learnt background, and two points whose test box (rows and columns 47-57 and
    57-67: one 6 px cell) is too small to be judged in cells: the whole dark area is compared instead."""
    road = _road(31, texture_std)
    return road, _learnt(road), np.array([[60.0, 50.0], [64.0, 54.0]])


@pytest.mark.parametrize("texture_std, plain", [(3.0, True), (9.0, False)])
def test_a_road_too_plain_to_show_its_texture_through_a_shadow_is_judged_by_even_dimming(texture_std, plain):
    """MIN_TEXTURE (6 grey levels): under a small shadow the road's texture is compared with the learnt road's
    only where it has some (generated with std 9, learnt 8: seen through the shadow whether or not the caller
    allows an even dimming to count). A plainer road's (std 3) is not trusted to show it (a live camera's noise
    is of that size), and an evenly dimmed box counts only where the caller allows it (the grouper's attached
    test, a caster beside it), not on its own."""
    road, bg, pts = _small_box(texture_std)
    img = road.copy()
    img[47:58, 57:68] = (road[47:58, 57:68] * 0.5).astype(np.uint8)
    assert bg.is_shadow(img, pts)
    assert bg.is_shadow(img, pts, plain_ok=False) != plain


@pytest.mark.parametrize("off_rows, shadow", [(1, True), (3, False)])
def test_on_a_plain_road_a_shadow_dims_nearly_all_of_its_box_evenly(off_rows, shadow):
    """FLAT_CORE_SHARE (85 %): where the road is too plain to show its texture, a box is a shadow only if nearly
    all of its darkened pixels are dimmed by the one factor: 1 of the 11 rows of a box all in shadow dimmed to 0.7
    instead of 0.5 is an edge; 3 of them (27 %) are a plain dark vehicle's other panel."""
    road, bg, pts = _small_box(2.0)
    img = road.copy()
    img[47:58, 57:68] = (road[47:58, 57:68] * 0.5).astype(np.uint8)
    img[48:48 + off_rows, 57:68] = (road[48:48 + off_rows, 57:68] * 0.7).astype(np.uint8)
    assert bg.is_shadow(img, pts) == shadow


def test_a_thin_shadows_tip_is_judged_with_its_body_towards_the_caster(monkeypatch):
    """TOWARD_MAX_POINTS: a low sun casts a dark car's shadow as a bar 4-6 pixels high across the next lanes,
    soft at its edges and its tip. A corner on the tip is judged on its own box (mostly road and penumbra: no
    shadow by the test) and on one reaching TOWARD_PX along the bar towards the car: a shadow attached to it."""
    road = _road(5, 9.0)
    bg = _learnt(road)
    img = road.astype(np.float32)
    img[50:72, 20:40] = 25  # the car
    f = np.ones_like(img)
    f[60:64, 40:140] = 0.5
    f[59, 40:140] = f[64, 40:140] = 0.75
    f[59:65, 135:140] = np.maximum(f[59:65, 135:140], np.linspace(0.5, 1.0, 5)[None, :])
    img = np.clip(img * f, 0, 255).astype(np.uint8)
    tip, caster = np.array([[137.0, 60.0]]), np.array([[25.0, 55.0], [35.0, 68.0], [38.0, 60.0]])
    assert not bg.is_shadow(img, tip)
    assert bg.is_attached_shadow(img, tip, caster)
    monkeypatch.setattr("appliance.background.TOWARD_MAX_POINTS", 0)
    assert not bg.is_attached_shadow(img, tip, caster)
