"""The vision numba kernels against their plain NumPy references (appliance.kernels_ref)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from appliance import kernels_ref as ref
from appliance.background import PAD_PX, shadow_at
from appliance.corners import select_spaced
from appliance.grouping import (alone_groups, assign_ids, components, fit_places, group_medians, group_summary,
                                isolate, pair_update, unbridge)
from appliance.tracker import extract_template, track_step


def _texture(seed: int, h: int = 120, w: int = 160) -> np.ndarray:
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 255, (h // 4, w // 4)).astype(np.uint8)
    return cv2.GaussianBlur(cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC), (3, 3), 0)


def test_template_matches_reference():
    """(The search's correlation is checked with track_step against its reference below.)"""
    img = _texture(0)
    t = np.zeros((9, 9), np.float32)
    assert extract_template(img, 50, 40, t)
    np.testing.assert_allclose(t, ref.template_ref(img, 50, 40, 9), atol=1e-6)
    assert ref.ncc_ref(img, t, 50, 40) == pytest.approx(1.0, abs=1e-5)
    flat = np.full((30, 30), 7, np.uint8)
    assert not extract_template(flat, 15, 15, t)


def _homography() -> tuple[np.ndarray, np.ndarray]:
    img = np.array([[0, 119], [159, 119], [55, 10], [105, 10]], np.float64)
    road = np.array([[-4, 0], [4, 0], [-4, 40], [4, 40]], np.float64)
    Hm, _ = cv2.findHomography(img, road)
    return Hm, np.linalg.inv(Hm)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_track_step_matches_reference(seed):
    rng = np.random.default_rng(seed)
    Hm, Hinv = _homography()
    prev = _texture(seed)
    # the whole image shifted by a known subpixel amount stands in for the next frame
    shift = rng.uniform(-2.5, 2.5, 2)
    M = np.float32([[1, 0, shift[0]], [0, 1, shift[1]]])
    cur = cv2.warpAffine(prev, M, (160, 120), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    n = 12
    px = np.column_stack([rng.uniform(30, 130, n), rng.uniform(40, 100, n)])
    tmpl = np.zeros((n, 9, 9), np.float32)
    for i in range(n):
        extract_template(prev, int(round(px[i, 0])), int(round(px[i, 1])), tmpl[i])
        px[i] = np.round(px[i])
    s = np.zeros((n, 4))
    for i in range(n):
        s[i, :2] = ref._project(Hm, px[i, 0], px[i, 1])
    s[:, 2:] = rng.normal(0, 0.5, (n, 2))
    P = np.tile(np.diag([0.05, 0.05, 4.0, 4.0]), (n, 1, 1))
    age = rng.integers(0, 6, n).astype(np.int32)
    args = dict(radius=3, ncc_min=0.7, q_acc=3.0, sigma_px=0.5, max_acc=8.0, max_lat=4.0)
    dt = 0.04
    expected = [
        ref.track_one_ref(cur, Hm, Hinv, (0.0, 0.0), dt, s[i].copy(), P[i].copy(), tmpl[i].astype(np.float64), age[i], **args)
        for i in range(n)
    ]
    alive = np.ones(n, np.bool_)
    s2, P2, px2 = s.copy(), P.copy(), px.copy()
    miss = np.zeros(n, np.int32)
    ncc = np.zeros(n, np.float32)
    track_step(cur, Hm, Hinv, 0.0, 0.0, dt, alive, px2, s2, P2, tmpl.copy(), age.copy(), miss, ncc, 3, 0.7, 3.0, 0.5,
               8.0, 4.0, 60.0, 2, 0.0)
    n_acc = 0
    errs = []
    for i, e in enumerate(expected):
        if e is None:
            assert not alive[i]
            continue
        accepted, se, Pe, me, best = e
        assert (miss[i] == 0) == accepted, i
        assert ncc[i] == pytest.approx(best, abs=1e-5)  # the search's best correlation
        np.testing.assert_allclose(s2[i], se, rtol=1e-6, atol=1e-8)
        np.testing.assert_allclose(P2[i], Pe, rtol=1e-6, atol=1e-10)
        if accepted:
            n_acc += 1
            np.testing.assert_allclose(px2[i], me, atol=1e-9)
            # and the match is where the image really moved: a 3-point parabola is biased by up to
            # ~0.4 px on a sharp NCC peak; 0.45 px still fails for an integer-only or wrong match
            np.testing.assert_allclose(px2[i] - px[i], shift, atol=0.45)
            errs.append(np.abs(px2[i] - px[i] - shift))
    assert n_acc >= n // 2
    assert np.mean(errs) < 0.2  # on average well below half a pixel


def test_select_spaced_matches_reference():
    rng = np.random.default_rng(7)
    cand = rng.uniform(0, 100, (300, 2))
    live = rng.uniform(0, 100, (40, 2))
    out = np.zeros(25, np.int64)
    k = select_spaced(cand, live, 6.0, 25, out)
    assert list(out[:k]) == ref.select_spaced_ref(cand, live, 6.0, 25)
    assert k > 5


@pytest.mark.parametrize("late_share", [0.0, 0.5])
def test_pair_graph_and_components_match_reference(late_share):
    """late_share: the share of slots that may link late (pairs first seen too far apart, see pair_update)."""
    rng = np.random.default_rng(11)
    n = 60
    # three rigid "vehicles" in one lane and one in another, plus noise features, over 20 frames; vehicles 0
    # and 1 close in from 6 m (first seen too far apart to link) to under 5 m (close enough to link late)
    base = rng.uniform(-1, 1, (n, 2)) * [0.8, 2.0]
    veh = rng.integers(0, 4, n)
    offs = np.array([[-1.7, 50.0], [-1.7, 56.0], [-1.7, 70.0], [1.7, 52.0]])
    speed = np.array([-15.0, -17.0, -14.0, -16.0])
    lane = np.where(veh == 3, 2, 1).astype(np.int32)
    live = np.sort(rng.choice(n, 50, replace=False)).astype(np.int64)
    late = rng.random(n) < late_share
    st_a = np.zeros((n, n), np.int8)
    st_b = st_a.copy()
    rng_a = np.zeros((n, n, 4), np.float32)
    rng_b = rng_a.copy()
    y0a = np.zeros((n, n), np.float32)
    y0b = y0a.copy()
    st_c, rng_c, y0c = st_a.copy(), rng_a.copy(), y0a.copy()  # no slot may link late
    for f in range(20):
        t = f * 0.04
        s = np.zeros((n, 4))
        s[:, :2] = base + offs[veh] + np.column_stack([np.zeros(n), speed[veh] * t]) + rng.normal(0, 0.03, (n, 2))
        motion = rng.integers(0, 3, n).astype(np.int8)  # standing / moving labels at random: the rule is the same
        pair_update(live, s, lane, motion, st_a, rng_a, y0a, 2.5, 5.0, 1.0, 0.5, 0.02, late)
        ref.pair_update_ref(live, s, lane, motion, st_b, rng_b, y0b, 2.5, 5.0, 1.0, 0.5, 0.02, late)
        np.testing.assert_array_equal(st_a, st_b)
        np.testing.assert_array_equal(rng_a, rng_b)
        np.testing.assert_array_equal(y0a, y0b)
        pair_update(live, s, lane, motion, st_c, rng_c, y0c, 2.5, 5.0, 1.0, 0.5, 0.02, np.zeros(n, np.bool_))
    if late_share:
        # pairs linked late that otherwise stay apart (they may join vehicles closing in: that is their point)
        assert np.count_nonzero((st_a == ref.LINKED) & (st_c == ref.FAR)) > 0
        return
    labels = np.full(n, -1, np.int64)
    components(live, st_a, labels)
    expect = ref.components_ref(live, st_b)
    assert {int(i): int(labels[i]) for i in live} == expect
    # the grouping separates what moves differently: no component mixes two vehicles
    for lab in set(expect.values()):
        members = [i for i, v in expect.items() if v == lab]
        assert len(set(veh[members])) == 1


def test_a_fragment_joins_one_part_of_a_vehicle_that_has_come_apart():
    """Slots 0-2 and 3-6 were two queued cars linked while crawling together; a roof fragment (7, 8) joined
    that one vehicle for good (MERGED to all its slots). Once the leader pulls away (its links to the follower
    dismissed) the fragment stays with the part it shares most pairs with and does not hold the cars together."""
    L, M = ref.LINKED, ref.MERGED_HI  # the higher slot is the fragment's
    state = np.zeros((9, 9), np.int8)
    for a, b in [(0, 1), (1, 2), (3, 4), (4, 5), (5, 6), (7, 8)]:
        state[a, b] = L
    for f in (7, 8):
        for h in range(7):
            state[h, f] = M
    labels = np.full(9, -1, np.int64)
    components(np.arange(9), state, labels)
    assert len(set(labels[:3])) == 1 and len(set(labels[3:])) == 1
    assert labels[0] != labels[3]  # the follower (4 slots) keeps the fragment, the leader goes its own way
    assert ref.components_ref(np.arange(9), state) == {i: int(labels[i]) for i in range(9)}
    state[2, 3] = L  # still linked: one vehicle
    components(np.arange(9), state, labels)
    assert len(set(labels)) == 1


def test_a_fragment_of_a_fragment_joins_through_it():
    """A roof (0, 1) joined a cab (2, 3) as a fragment, and the cab was later found to be a part of a
    trailer's vehicle (4-6): all three are one vehicle, whichever slots they hold."""
    state = np.zeros((7, 7), np.int8)
    for a, b in [(0, 1), (2, 3), (4, 5), (5, 6)]:
        state[a, b] = ref.LINKED
    state[0, 2] = ref.MERGED_LO  # 0's feature is the fragment (of 2's vehicle)
    state[2, 4] = ref.MERGED_LO
    labels = np.full(7, -1, np.int64)
    components(np.arange(7), state, labels)
    assert set(labels) == {0}
    assert ref.components_ref(np.arange(7), state) == {i: 0 for i in range(7)}


def test_components_with_fragments_match_reference():
    rng = np.random.default_rng(5)
    for trial in range(30):
        n = int(rng.integers(5, 40))
        state = np.zeros((n, n), np.int8)
        iu = np.triu_indices(n, 1)
        state[iu] = rng.choice([0, 1, 2, 3, 4, 5], len(iu[0]), p=[0.45, 0.08, 0.38, 0.02, 0.02, 0.05])
        live = np.sort(rng.choice(n, int(rng.integers(1, n + 1)), replace=False)).astype(np.int64)
        labels = np.full(n, -1, np.int64)
        components(live, state, labels)
        assert {int(i): int(labels[i]) for i in live} == ref.components_ref(live, state), trial


def test_unbridge_and_isolate_match_reference():
    """Random pair graphs over owned (three vehicles) and unowned features, with new features among them."""
    rng = np.random.default_rng(5)
    changed = 0
    for trial in range(40):
        n = 40
        live = np.sort(rng.choice(n, 32, replace=False)).astype(np.int64)
        owner = np.where(rng.random(n) < 0.6, rng.integers(0, 3, n), -1).astype(np.int64)
        s = np.zeros((n, 4))
        s[:, :2] = rng.uniform(-3, 3, (n, 2)) + [0.0, 50.0]
        state = np.triu(rng.choice([ref.UNSEEN, ref.LINKED, ref.APART, ref.FAR], (n, n), p=[0.3, 0.5, 0.1, 0.1]),
                        1).astype(np.int8)
        new = rng.choice(live, 6, replace=False).astype(np.int64)
        st_a, st_b = state.copy(), state.copy()
        kept = unbridge(new, live, owner, s, st_a)
        np.testing.assert_array_equal(kept, ref.unbridge_ref(new, live, owner, s, st_b), err_msg=str(trial))
        np.testing.assert_array_equal(st_a, st_b, err_msg=str(trial))
        isolate(new, kept, live, owner, st_a)
        ref.isolate_ref(new, kept, live, owner, st_b)
        np.testing.assert_array_equal(st_a, st_b, err_msg=str(trial))
        changed += bool((st_a != state).any())
    assert changed >= 30  # most graphs had a new feature bridging two vehicles or a group of none


def test_a_new_feature_between_two_queued_vehicles_keeps_only_the_nearer():
    """Two reported vehicles 6 m apart in a queue; a corner found between them links to both. It stays
    linked to the one it is nearer (its own features and an unowned neighbour keep their links)."""
    n = 8
    live = np.arange(n, dtype=np.int64)
    owner = np.array([0, 0, 0, 1, 1, 1, -1, -1], np.int64)
    s = np.zeros((n, 4))
    s[:, 1] = [50.0, 51.0, 52.0, 58.0, 59.0, 60.0, 54.0, 53.5]  # slot 6: the new corner, 2 m behind vehicle 0
    state = np.zeros((n, n), np.int8)
    for i, j in [(0, 1), (1, 2), (3, 4), (4, 5), (2, 6), (3, 6), (6, 7)]:
        state[i, j] = ref.LINKED
    kept = unbridge(np.array([6], np.int64), live, owner, s, state)
    assert list(kept) == [0]
    assert state[2, 6] == ref.LINKED and state[3, 6] == ref.APART and state[6, 7] == ref.LINKED
    labels = np.full(n, -1, np.int64)
    components(live, state, labels)
    assert labels[3] != labels[2] == labels[6]
    isolate(np.array([6], np.int64), kept, live, owner, state)
    assert state[2, 6] == ref.LINKED and state[6, 7] == ref.APART  # only its vehicle's links are left


def test_assign_ids_matches_reference():
    """Ids follow the features from frame to frame: random components over random earlier ids, as the
    grouper's Python reference assigns them (biggest component first, majority id with reported ids first, new ids
    counted on)."""
    rng = np.random.default_rng(11)
    for trial in range(40):
        n = int(rng.integers(1, 60))
        live = np.sort(rng.choice(80, n, replace=False)).astype(np.int64)
        labels = np.full(80, -1, np.int64)
        labels[live] = rng.integers(0, max(1, n // 3), n)
        fvid = np.where(rng.random(80) < 0.3, -1, rng.integers(1, 8, 80)).astype(np.int64)
        fvid_ref = fvid.copy()
        reported = np.flatnonzero(rng.random(8) < 0.3).astype(np.int64)
        order, starts, vids, nxt = assign_ids(live, labels, fvid, 50, reported)
        expect, nxt_ref = ref.assign_ids_ref(live, labels, fvid_ref, 50, reported)
        got = {int(vids[r]): order[starts[r]:starts[r + 1]] for r in range(len(vids))}
        assert list(got) == list(expect) and nxt == nxt_ref, trial
        for vid, members in expect.items():
            np.testing.assert_array_equal(got[vid], members)
        np.testing.assert_array_equal(fvid, fvid_ref)


def test_a_component_keeps_the_id_of_the_reported_vehicle_in_it():
    """A queued car reported long ago, two of its corners left, links up with a small group not yet reported
    (three corners found on it as it crawled): the component is that vehicle still, its count and its time in
    the region going on; a group not yet reported has only a provisional id. Without reported vehicles the
    most frequent id wins."""
    live = np.arange(5, dtype=np.int64)
    labels = np.zeros(5, np.int64)
    order, starts, vids, nxt = assign_ids(live, labels, np.array([7, 7, 5, 5, 5], np.int64), 50,
                                          np.array([3, 7], np.int64))
    assert vids.tolist() == [7] and nxt == 50
    order, starts, vids, nxt = assign_ids(live, labels, np.array([7, 7, 5, 5, 5], np.int64), 50,
                                          np.zeros(0, np.int64))
    assert vids.tolist() == [5]
    # one corner of the car in the standing group behind it (9 of id 5), its other 3 in a group of their own:
    # the car stays with those 3
    live = np.arange(13, dtype=np.int64)
    labels = np.array([0] * 10 + [1] * 3, np.int64)
    order, starts, vids, nxt = assign_ids(live, labels, np.array([5] * 9 + [7] * 4, np.int64), 50,
                                          np.array([7], np.int64))
    assert vids.tolist() == [5, 7] and nxt == 50


def test_fit_places_matches_reference():
    """A group's length fit, frame by frame over a vehicle's approach (features at random heights and places,
    some joining late, one fitted before for another group), gives the reference's far end and its height
    magnification exactly."""
    rng = np.random.default_rng(12)
    n = 14
    place, k = rng.uniform(0.0, 6.0, n), rng.uniform(1.0, 1.4, n)
    fit, fit_vid = np.zeros((n, 5)), np.full(n, -1, np.int64)
    fit_vid[3] = 9
    fit2, fit_vid2 = fit.copy(), fit_vid.copy()
    members = np.arange(n, dtype=np.int64)
    seen = 0
    for f in range(40):
        d = 80.0 - 0.8 * f
        age = np.maximum(f - np.repeat([0, 6, 20], [8, 4, 2]), -1).astype(np.int32)
        s = np.zeros((n, 4))
        s[:, 1] = k * (d + place) + rng.normal(0.0, 0.05, n)
        live = members[age >= 0]
        a = fit_places(live, age, s, fit, fit_vid, 5, d, 0.0, 1.82, 10, 2.25, 1.0)
        b = ref.fit_places_ref(live, age, s, fit2, fit_vid2, 5, d, 0.0, 1.82, 10, 2.25, 1.0)
        assert (np.isnan(a).all() and np.isnan(b).all()) or a == b, f
        seen += not np.isnan(a[0])
        np.testing.assert_array_equal(fit, fit2)
    assert seen > 10


def test_fit_places_falls_back_to_the_median_and_waits_for_a_late_joiner_further_out():
    """Three level features 0, 3 and 7 m behind the near end, none within a metre of another: the far end is
    their median (3 m). A feature that has just joined and lies further out than all of them: no answer yet."""
    args = (0.0, 1.82, 10, 2.25, 1.0)
    members = np.arange(3, dtype=np.int64)
    fit, fit_vid = np.zeros((4, 5)), np.full(4, -1, np.int64)
    fit2, fit_vid2 = fit.copy(), fit_vid.copy()
    s = np.zeros((4, 4))
    age = np.full(4, 5, np.int32)
    for f in range(12):
        d = 60.0 - 2.0 * f
        s[:3, 1] = d + np.array([0.0, 3.0, 7.0])
        a = fit_places(members, age, s, fit, fit_vid, 5, d, *args)
        b = ref.fit_places_ref(members, age, s, fit2, fit_vid2, 5, d, *args)
    assert a[0] == pytest.approx(3.0, abs=1e-9) and a[1] == pytest.approx(1.0) and b == a
    s[3, 1] = d + 12.0
    both = np.arange(4, dtype=np.int64)
    assert np.isnan(fit_places(both, age, s, fit.copy(), fit_vid.copy(), 5, d, *args)[0])
    assert np.isnan(ref.fit_places_ref(both, age, s, fit2, fit_vid2, 5, d, *args)[0])


def test_group_summary_matches_reference():
    """Random groups, some with standing or slow features among moving ones: the same body, near end, span,
    velocity, spot speed and place across the road as the NumPy reference."""
    rng = np.random.default_rng(13)
    own_spot = 0
    for trial in range(150):
        n = 40
        kind = rng.random(n)
        vy = np.where(kind < 0.2, rng.normal(0, 0.4, n),
                      np.where(kind < 0.3, rng.normal(-6, 2, n), rng.normal(-15, 2, n)))
        s = np.column_stack([rng.uniform(-4, 4, n), rng.uniform(20, 80, n), rng.normal(0, 0.3, n), vy])
        px = np.column_stack([rng.uniform(0, 640, n), rng.uniform(0, 480, n)])
        age = rng.integers(0, 8, n).astype(np.int32)
        members = np.sort(rng.choice(n, int(rng.integers(1, 15)), replace=False)).astype(np.int64)
        got = group_summary(members, s, px, age, 3.0, 1.0, 4.0, 1.0, 1.08, 10.0)
        want = ref.group_summary_ref(members, s, px, age, 3.0, 1.0, 4.0, 1.0, 1.08, 10.0)
        np.testing.assert_array_equal(got[0], want[0])
        assert got[1] == want[1] and list(got[2:]) == list(want[2:]), trial
        own_spot += got[5] != got[4]
    assert own_spot >= 5  # the spot speed comes from its own band of features, not only the velocity's


def test_a_group_whose_every_corner_is_too_fast_or_too_slow_still_has_a_near_end():
    """Four corners 3 frames old, two at 2 m/s and two at 30 m/s: those at 30 are over 1.08 times their median
    (16 m/s), those at 2 under half of it. The near end is then the lowest not too fast, as before the slow
    rule, in the kernel and in the reference."""
    s = np.zeros((4, 4))
    s[:, 1] = [60.0, 61.0, 62.0, 63.0]
    s[:, 3] = [-2.0, -2.0, -30.0, -30.0]
    px = np.column_stack([np.full(4, 300.0), 200.0 - 2.0 * s[:, 1]])
    age = np.full(4, 3, np.int32)
    members = np.arange(4, dtype=np.int64)
    for f in (group_summary, ref.group_summary_ref):
        assert f(members, s, px, age, 3.0, 1.0, 4.0, 1.0, 1.08, 10.0)[1] == 0, f.__name__


@pytest.mark.parametrize("speed, expect_near", [(18.0, 4), (6.0, 5)])
def test_near_end_is_no_faster_feature_below_the_vehicle(speed: float, expect_near: int):
    """A car's settled features move at one speed; a feature lower in the image moving 15 % faster (the top of
    the vehicle ahead, linked through a new corner) is not its near end at traffic speeds, both in the kernel
    and in the reference. In a crawl speed ratios say nothing: the lowest feature stays the near end."""
    n = 6
    s = np.zeros((n, 4))
    s[:, 1] = [60.0, 61.0, 62.0, 63.5, 59.0, 55.0]
    s[:, 3] = -speed
    s[5, 3] = -speed * 1.15
    px = np.column_stack([np.full(n, 300.0), 200.0 - 2.0 * s[:, 1]])  # nearer the camera: lower in the image
    age = np.full(n, 10, np.int32)
    members = np.arange(n, dtype=np.int64)
    for f in (group_summary, ref.group_summary_ref):
        got = f(members, s, px, age, 3.0, 1.0, 4.0, 1.0, 1.08, 10.0)
        assert got[1] == expect_near, f.__name__


def test_group_medians_and_alone_groups_match_reference():
    """The per-group medians, and the late-link test of small groups against each other and vehicle groups
    (random lanes, places and speeds around the thresholds, some vehicles too small to hold a part)."""
    rng = np.random.default_rng(5)
    s = rng.normal(0, 10, (40, 4))
    members = rng.permutation(40)[:30].astype(np.int64)
    starts = np.array([0, 1, 3, 6, 10, 17, 30], np.int64)
    age = rng.integers(0, 20, 40).astype(np.int32)
    med = group_medians(members, starts, s, age)
    for g in range(len(starts) - 1):
        m = members[starts[g]:starts[g + 1]]
        np.testing.assert_array_equal(med[g], [np.median(s[m, 0]), np.median(s[m, 1]), np.median(s[m, 3]),
                                               age[m].max()])
    verdicts = []
    for trial in range(300):
        ns, nb = rng.integers(1, 8), rng.integers(0, 10)
        sl = rng.integers(1, 4, ns).astype(np.int64)
        sx, sy = rng.uniform(-7, 7, ns), rng.uniform(20, 90, ns)
        sv = rng.choice([-1.0, 1.0], ns) * rng.uniform(4, 30, ns)
        big = np.column_stack([rng.integers(1, 4, nb), rng.uniform(-7, 7, nb), rng.uniform(20, 90, nb),
                               rng.choice([-1.0, 1.0, 0.0], nb, p=[0.45, 0.45, 0.1]) * rng.uniform(4, 30, nb),
                               rng.uniform(-7, 0, nb), rng.uniform(0, 7, nb), rng.uniform(18.75, 25, nb),
                               rng.integers(0, 2, nb)]).astype(np.float64).reshape(-1, 8)
        k_max = 1.0 if trial % 5 == 0 else 1.9
        got = alone_groups(sl, sx, sy, sv, big, 0.5, -20.0, k_max)
        np.testing.assert_array_equal(got, ref.alone_groups_ref(sl, sx, sy, sv, big, 0.5, -20.0, k_max))
        verdicts += list(got)
    assert 0.1 < np.mean(verdicts) < 0.9  # both answers are exercised


@pytest.mark.parametrize("dy, dx, ratio, alone", [
    (14.0, 3.5, 1.0, False), (16.0, 3.5, 1.0, True),  # LATE_BESIDE_M: 15 m along the road
    (0.0, 5.5, 1.0, False), (0.0, 6.5, 1.0, True),  # LATE_BESIDE_X_M: 6 m across
    (0.0, 3.5, 0.65, True), (0.0, 3.5, 0.75, False), (0.0, 3.5, 1.45, False), (0.0, 3.5, 1.55, True),  # _K
])
def test_a_small_group_is_alone_only_without_a_next_lane_group_moving_beside_it(dy, dx, ratio, alone):
    """The late-link windows from both sides: a small group of lane 2 beside one of lane 1 (dy along the road,
    dx across, at ratio times its speed) may not link late; one further off, or far slower or faster, may."""
    sl = np.array([2, 1], np.int64)
    sx, sy = np.array([0.0, -dx]), np.array([50.0, 50.0 + dy])
    sv = np.array([-20.0, -20.0 * ratio])
    got = alone_groups(sl, sx, sy, sv, np.zeros((0, 8)), 0.0, -20.0, 1.9)
    assert bool(got[0]) == alone


@pytest.mark.parametrize("gap, alone", [(2.4, False), (2.6, True)])
def test_a_small_group_beside_a_vehicles_footprint_is_alone_only_beyond_the_host_margin(gap, alone):
    """LATE_HOST_X_M (2.5 m): a small group this far across the road from a vehicle of its lane, level with it,
    could be a part of it (a mirror, a flank seen at the lane line) and may not link late; further off it may."""
    sl, sx, sy, sv = np.array([2], np.int64), np.array([0.0]), np.array([50.0]), np.array([-20.0])
    big = np.array([[2, gap + 1.0, 45.0, -20.0, gap, gap + 2.0, 4.5, 1]], np.float64)  # lane, x, near, v, x_lo..
    assert bool(alone_groups(sl, sx, sy, sv, big, 0.0, -20.0, 1.9)[0]) == alone


def _shadow_cases(seed: int, n: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(frame, road, feature points) with the road's texture under a shadow, a dark vehicle, an even dimming,
    a half-dimmed box with a bright edge: each boundary of the shadow test is crossed one way or the other."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        road = np.clip(rng.normal(120, rng.uniform(1, 20), (60, 80)), 0, 255).astype(np.uint8)
        img = road.astype(np.float32)
        x0, y0 = rng.integers(0, 50), rng.integers(0, 40)
        x1, y1 = x0 + rng.integers(1, 40), y0 + rng.integers(1, 30)
        box = img[y0:y1, x0:x1]
        kind = i % 4
        if kind == 0:
            box[rng.integers(0, box.shape[0]):] *= rng.uniform(0.3, 0.8)
        elif kind == 1:
            body = box[box.shape[0] // 4:, box.shape[1] // 3:]
            body[:] = rng.normal(60, 10, body.shape)
        elif kind == 2:
            box *= rng.uniform(0.3, 0.9)
            box += rng.normal(0, 3, box.shape)
        else:
            box[:, : box.shape[1] // 2] *= 0.5
            box[:2] = 250
        frame = np.clip(img, 0, 255).astype(np.uint8)
        pts = np.stack([rng.uniform(x0, x1, 4), rng.uniform(y0, y1, 4)], axis=1)
        out.append((frame, road, pts))
    return out


def test_shadow_kernel_matches_reference():
    """The shadow test's kernel (its box round the points, then the test) gives the NumPy reference's answer on
    every case, shadows and not."""
    answers = []
    for frame, road, pts in _shadow_cases(5, 1500):
        x0, y0 = np.floor(pts.min(axis=0)).astype(int) - PAD_PX
        x1, y1 = np.ceil(pts.max(axis=0)).astype(int) + PAD_PX + 1
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, 80), min(y1, 60)
        for plain_ok in (True, False):
            want = x1 - x0 >= 3 and y1 - y0 >= 3 and ref.shadow_box_ref(frame[y0:y1, x0:x1], road[y0:y1, x0:x1],
                                                                         plain_ok)
            assert bool(shadow_at(frame, road, pts, plain_ok)) == want
            answers.append(want)
    assert 0.2 < np.mean(answers) < 0.8  # both answers, often


def test_a_feature_missing_its_match_at_a_speed_no_vehicle_reaches_is_dropped():
    """A new corner's velocity comes from one frame of optical flow; flow matched to something else can give
    hundreds of metres a second, which nothing corrects while the feature misses its match (one drifted 35 m in
    a frame into a car's group on a night scene, and that car crossed its count line at 3339 km/h). Missing at
    such a speed, it is dropped; at a vehicle's speed it may miss a frame or two."""
    Hm, Hinv = _homography()
    img = _texture(5)
    other = _texture(6)  # the templates come from another picture: nothing matches
    n = 4
    px = np.array([[60.0, 60.0], [80.0, 60.0], [100.0, 60.0], [80.0, 40.0]])
    tmpl = np.zeros((n, 9, 9), np.float32)
    s = np.zeros((n, 4))
    for i in range(n):
        extract_template(other, int(px[i, 0]), int(px[i, 1]), tmpl[i])
        s[i, :2] = ref._project(Hm, px[i, 0], px[i, 1])
    max_speed = 60.0
    s[:, 3] = [-5.0, -max_speed + 1.0, -max_speed - 1.0, -300.0]  # each predicted inside the image
    P = np.tile(np.diag([0.05, 0.05, 4.0, 4.0]), (n, 1, 1))
    alive = np.ones(n, np.bool_)
    miss = np.zeros(n, np.int32)
    track_step(img, Hm, Hinv, 0.0, 0.0, 0.04, alive, px, s, P, tmpl, np.zeros(n, np.int32), miss,
               np.zeros(n, np.float32), 3, 0.99, 3.0, 0.5, 8.0, 4.0, max_speed, 2, 0.0)
    assert miss[alive].tolist() == [1, 1]
    assert alive.tolist() == [True, True, False, False]
