"""Hand-count comparisons: site-from-counts on the real CDnet clip, matching rules, full replay."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from appliance.config import load_site
from tools.clip_variants import make_variant
from tools.evaluate import compare_with_counts
from tools.handcount import load_counts, site_from_counts


@pytest.fixture(scope="module")
def counts_file(shared_data):
    p = shared_data / "cdnet-highway" / "counts.json"
    if not p.exists():
        pytest.skip("cdnet-highway/counts.json missing")
    return p


@pytest.fixture(scope="module")
def site_file(counts_file, tmp_path_factory):
    out = tmp_path_factory.mktemp("hw") / "site.toml"
    r = CliRunner().invoke(site_from_counts, [str(counts_file), "--out", str(out)])
    assert r.exit_code == 0, r.output
    return out


def test_site_from_counts_makes_a_valid_site(site_file, counts_file):
    site = load_site(site_file)
    counts = json.loads(counts_file.read_text())
    assert [ln.id for ln in site.lanes] == [1, 2]
    assert (site.source.width, site.source.height) == tuple(counts["size"])
    # the count line is image row 175, documented as road Y = 8.59 m
    for lane in site.lanes:
        assert lane.count_y_m == pytest.approx(8.59, abs=0.05)
    assert [lp.channel for lp in site.loops] == [1, 2]
    # loop zones: documented as road Y 6.34 .. 10.84 m
    for lp in site.loops:
        assert lp.y_m == pytest.approx(6.34, abs=0.1)
        assert lp.length_m == pytest.approx(4.5, abs=0.15)
    url = site.source.url.removeprefix("images:")
    assert (site_file.parent / url).parent.resolve() == (counts_file.parent / "input").resolve()


def test_site_from_counts_rejects_bad_file(tmp_path):
    bad = tmp_path / "counts.json"
    bad.write_text(json.dumps({"size": [320, 240], "lanes": []}))
    r = CliRunner().invoke(site_from_counts, [str(bad), "--out", str(tmp_path / "s.toml")])
    assert r.exit_code != 0 and "missing key 'count_line_px'" in r.output


def test_matching_rule(counts_file):
    counts = load_counts(counts_file)
    hand = counts["crossings"]
    res = [{"frame": c["frame"] + 2, "lane": c["lane"]} for i, c in enumerate(hand) if i not in (0, 6)]
    res.append({"frame": hand[5]["frame"] + 40, "lane": hand[5]["lane"]})  # an extra, far in time
    res.append({"frame": hand[6]["frame"], "lane": 3 - hand[6]["lane"]})  # right time, wrong lane
    cmp = compare_with_counts(counts, res, tolerance_frames=3)
    assert len(cmp.matches) == len(hand) - 2
    assert {c["frame"] for c in cmp.missed} == {hand[0]["frame"], hand[6]["frame"]}
    assert len(cmp.extra) == 2
    tight = compare_with_counts(counts, res, tolerance_frames=1)
    assert len(tight.matches) == 0
    # a crossing whose report was held is seen frames after it crossed: its time says when it crossed
    fps = float(counts.get("fps", 25.0))
    held = [{"frame": c["frame"] + 30, "t": (c["frame"] + 1) / fps, "lane": c["lane"]} for c in hand]
    assert len(compare_with_counts(counts, held, tolerance_frames=3).matches) == len(hand)


def _replay_and_evaluate(video: Path, site_file: Path, counts_file: Path, out: Path) -> tuple[dict[int, list[int]], str]:
    """`roadwatch replay` then `roadwatch evaluate` as subprocesses: per-lane rows (hand, result, matched,
    missed, extra, diff) and the evaluation's text."""
    r = subprocess.run([sys.executable, "-m", "tools.cli", "replay", str(video), "--config", str(site_file),
                        "--fps", "25", "--out", str(out), "--vehicles"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "1700 frames" in r.stdout
    r = subprocess.run([sys.executable, "-m", "tools.cli", "evaluate", "--counts", str(counts_file),
                        "--results", str(out)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    rows = {int(ln.split()[0]): [int(x) for x in ln.split()[1:]] for ln in r.stdout.splitlines()
            if ln.strip() and ln.split()[0].isdigit()}
    return rows, r.stdout


def test_replay_and_evaluate_real_clip(site_file, counts_file, tmp_path):
    """The whole chain from the command line on the 1700-frame clip (~15 s)."""
    video = counts_file.parent / "input" / "in%06d.jpg"
    rows, text = _replay_and_evaluate(video, site_file, counts_file, tmp_path / "res.sqlite")
    hand = {1: 17, 2: 10}
    # the target on real clips: per-lane counts within 1 vehicle of the hand count
    for lane, n in hand.items():
        assert rows[lane][0] == n and abs(rows[lane][1] - n) <= 1, text
    matched = sum(rows[lane][2] for lane in hand)
    # a match is the same lane within 4 frames. A working tracker finds 23-26 of the 27 (23 since
    # the hold-and-backfill change: two crossings land 10-11 frames late and the box truck's
    # neighbour is put in the wrong lane); a broken one finds few or none
    assert matched >= 23, text
    # extras (fragments of the box truck, a car pulled into lane 2 beside it) were 3-4 at the last
    # runs (12 earlier); the target is +-1 per lane, this guards against getting worse
    assert sum(rows[lane][4] for lane in hand) <= 8, text


# the calibration's principal point lies at x 276 of 320 (the frame is likely a crop): 232 black columns on the
# right put it at the centre, so that the camera is known and heights are undone ("centred")
CENTRING_PAD_PX = 232


@pytest.mark.parametrize("kind", ["reversed", "centred",
                                  pytest.param("dark", marks=pytest.mark.slow),
                                  pytest.param("drift", marks=pytest.mark.slow),
                                  pytest.param("repeat", marks=pytest.mark.slow),
                                  pytest.param("rain", marks=pytest.mark.slow)])
def test_real_clip_variants_count_within_one_per_lane(counts_file, tmp_path, kind):
    """The target on real clips (each lane within 1 of the hand count) on footage unlike the clip's own.
    Reversed: receding traffic entering over the image's bottom edge. This clip's calibration fits no centred
    camera, so lengths are not height-corrected (17-25 m) and a vehicle is first seen with its front
    already over the line 12 m from the edge; it counts when first seen straddling it (7 of 17 in lane 1
    before that rule). The hand frames, mirrored, are the rear's, so crossings are not matched in time here.
    Dark: roofs seen as groups of their own crossed 0.37 s behind their cars (lane 1 +2 before the
    speed-dependent shortest headway). Centred: with heights undone (an 8.1 m camera, roofs 1.2 times as fast
    in projection), roofs reported apart from their cars made lane 2 +3 (4 extras) until a feature found
    between the two could join them (PART_MIN_MPS); lane 2 then read 8 of 10 (the grey SUV of frame 891 rode in
    one 33 m group with the sedan 1.4 s ahead of it, the SUV of frame 1654 was lost 1 s behind a sedan) until a
    vehicle measured longer than any is cut in two (grouping.LONGEST_M): both count since (the second 5 frames
    late). Rain: streaks left one auto-picked fiducial, whose false matches ran the stabiliser's
    offset away by 100 px on this fixed camera (lanes 4 of 17 and 2 of 10) until a lone fiducial could move it
    1 px a frame at most."""
    clip = (make_variant(counts_file, tmp_path, "original", pad_right=CENTRING_PAD_PX) if kind == "centred"
            else make_variant(counts_file, tmp_path, kind))
    site = tmp_path / "site.toml"
    r = CliRunner().invoke(site_from_counts, [str(clip), "--out", str(site)])
    assert r.exit_code == 0, r.output
    rows, text = _replay_and_evaluate(tmp_path / "input" / "in%06d.jpg", site, clip, tmp_path / "res.sqlite")
    for lane, n in {1: 17, 2: 10}.items():
        assert rows[lane][0] == n and abs(rows[lane][1] - n) <= 1, text
