"""Loop actuations reach the results of a plain replay (without --vehicles), so evaluate compares them.

The "0 actuations per channel" seen in evaluate came from replay writing loop events only with --vehicles.
"""

from __future__ import annotations

import csv
import os
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest


def roadwatch(*args: str, cwd: Path) -> str:
    env = dict(os.environ)
    r = subprocess.run([sys.executable, "-m", "tools.cli", *args], cwd=cwd, env=env, capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    return r.stdout


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("loops") / "free-flow"
    roadwatch("simulate", "--preset", "free-flow", "--seed", "23", "--seconds", "20", "--out", str(d), "-q",
              cwd=Path(__file__).resolve().parent.parent)
    return d


def _truth_per_channel(d: Path, since: float = float("-inf")) -> dict[int, int]:
    out: dict[int, int] = {}
    for r in csv.DictReader(open(d / "truth" / "loop_events.csv")):
        if float(r["t_on"]) >= since:
            out[int(r["channel"])] = out.get(int(r["channel"]), 0) + 1
    return out


@pytest.mark.parametrize("suffix", ["sqlite", "csv"])
def test_plain_replay_writes_loop_events(scene, tmp_path, suffix):
    repo = Path(__file__).resolve().parent.parent
    out = tmp_path / f"r.{suffix}"
    # the simulator's exact trajectories (a perfect tracker): loop actuations must then match the truth's
    roadwatch("replay", "--config", str(scene / "site.toml"), "--truth-tracks", str(scene / "truth"),
              "--out", str(out), cwd=repo)
    if suffix == "sqlite":
        with sqlite3.connect(out) as c:
            rows = c.execute("SELECT channel, COUNT(*) FROM loop_events GROUP BY channel").fetchall()
        got = {int(ch): int(n) for ch, n in rows}
    else:
        got = {}
        for r in csv.DictReader(open(tmp_path / "r_loop_events.csv")):
            got[int(r["channel"])] = got.get(int(r["channel"]), 0) + 1
    want = _truth_per_channel(scene)
    assert sum(want.values()) >= 4  # 20 s of free flow puts a few vehicles over each loop
    # separate vehicles (free flow) through a perfect tracker give the truth's actuations; 1 per channel
    # allows a vehicle on a loop at the clip's end (the truth closes it, the replay's last frame may not)
    for ch, n in want.items():
        assert abs(got.get(ch, 0) - n) <= 1, (got, want)
    report = roadwatch("evaluate", "--truth", str(scene / "truth"), "--results", str(out), cwd=repo)
    line = next(ln for ln in report.splitlines() if ln.startswith("Loop actuations"))
    assert "/0" not in line.replace("/0.", ""), line


@pytest.mark.slow
def test_tracked_loop_actuations_match_the_truth_in_dense_traffic(tmp_path):
    """The vision pipeline's loop actuations against the truth's in dense traffic: no second actuation for
    a vehicle whose group comes apart over a loop, no vehicle lost. Measured here: -4.5 % over the four
    loops (150 of 157; worst loop -3 of 38; -3.8 % with the earlier length estimate). The loops' dropout
    bridging is tested in test_measures_core: since the grouping keeps standing and moving features apart,
    few groups come apart over these loops and this scene gives +1.3 % without bridging (it gave +5.7 %
    before). The 320 s sweeps of the same preset, seeds 11 and 12: -5 % .. +4 % per loop, sums within 1.2 %.
    The bound on this short clip's sum, 5 %, is that per-loop spread."""
    repo = Path(__file__).resolve().parent.parent
    d = tmp_path / "dense"
    roadwatch("simulate", "--preset", "dense", "--seed", "2", "--seconds", "90", "--out", str(d), "-q", cwd=repo)
    out = tmp_path / "r.sqlite"
    roadwatch("replay", str(d / "video.mp4"), "--config", str(d / "site.toml"), "--out", str(out), cwd=repo)
    # from 10 s on: the first seconds are lost to start-up (background, vehicles already in view)
    with sqlite3.connect(out) as c:
        got = dict(c.execute("SELECT channel, COUNT(*) FROM loop_events WHERE t_on >= 10 GROUP BY channel").fetchall())
    want = _truth_per_channel(d, since=10.0)
    total = sum(want.values())
    assert total >= 120  # four lanes of dense traffic
    for ch, n in want.items():
        assert abs(got.get(ch, 0) - n) <= max(4, 0.1 * n), (got, want)
    assert abs(sum(got.values()) - total) <= 0.05 * total, (got, want)


def _on_intervals(rows) -> dict[str, list[tuple[float, float]]]:
    out: dict[str, list] = {}
    for loop_id, t_on, t_off in rows:
        out.setdefault(loop_id, []).append((float(t_on), float(t_off)))
    return out


def _overlap(a: list, b: list) -> float:
    return sum(max(0.0, min(y, e) - max(x, s)) for x, y in a for s, e in b)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [11, 12])
def test_loops_under_a_standing_queue_stay_on(tmp_path, seed):
    """A red light's queue stands over both loops for about a minute (stopped-queue, first 130 s: the stand and
    the discharge). Its cars lose their features as they stand: the tracker's actuations alone covered 12 %
    (loop 1) and 38 % (loop 2) of the loops' true on-time over a whole 320 s scene; the image's standing
    calls hold the loops. Measured (the replay's actuations against the truth's), loops 1 and 2: seed 11
    covers 90 and 90 % of the true on-time, the actuations summing to 108 and 99 % of it; seed 12 91 and 89 %,
    108 and 97 %. Bounds: 80 % covered, the sum within 15 % (a queued car's roof covers the loop behind it, so
    a gap in the queue over a loop reads occupied; the tracker's actuations of crawling cars end late)."""
    repo = Path(__file__).resolve().parent.parent
    d = tmp_path / "queue"
    roadwatch("simulate", "--preset", "stopped-queue", "--seed", str(seed), "--seconds", "130", "--out", str(d),
              "-q", cwd=repo)
    out = tmp_path / "r.sqlite"
    roadwatch("replay", str(d / "video.mp4"), "--config", str(d / "site.toml"), "--out", str(out), cwd=repo)
    with sqlite3.connect(out) as c:
        got = _on_intervals(c.execute("SELECT loop_id, t_on, t_off FROM loop_events").fetchall())
    want = _on_intervals((r["loop_id"], r["t_on"], r["t_off"]) for r in csv.DictReader(open(d / "truth" /
                                                                                              "loop_events.csv")))
    for loop_id, truth in want.items():
        on = sum(b - a for a, b in truth)
        assert on > 60.0  # the queue stood over it
        mine = got.get(loop_id, [])
        print(loop_id, f"covered {_overlap(truth, mine) / on:.3f} sum {sum(b - a for a, b in mine) / on:.3f}")
        assert _overlap(truth, mine) >= 0.80 * on, (loop_id, mine)
        assert abs(sum(b - a for a, b in mine) - on) <= 0.15 * on, (loop_id, mine)
