"""The service as a real subprocess on the real clip, SIGKILLed at random moments and restarted:
every completed period ends up in the store exactly once, identical to a run without kills."""

from __future__ import annotations

import random
import sqlite3
import subprocess
import threading
import time
from pathlib import Path

import pytest

from test_service_sitefiles import cdnet_site, start

FPS = 25.0


def _dump(db: Path) -> dict:
    conn = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
    out = {
        "periods": conn.execute(
            "SELECT lane, period_start, period_s, count, flow_vph, density_vpkm, speed_kmh, time_mean_speed_kmh,"
            " occupancy_pct, speed85_kmh, headway_s, class_counts, partial, quality FROM periods"
            " ORDER BY period_start, lane").fetchall(),
        "events": conn.execute(
            "SELECT loop_id, channel, lane, vehicle_id, t_on, t_off, wall_on, wall_off, speed_kmh, length_m"
            " FROM loop_events ORDER BY wall_on, loop_id").fetchall(),
        "vehicles": conn.execute(
            "SELECT vehicle_id, lane, wall_entry, wall_exit, speed_kmh, length_m, length_class FROM vehicles"
            " ORDER BY wall_exit, vehicle_id").fetchall(),
        "dupes": conn.execute("SELECT COUNT(*) FROM (SELECT lane, period_start, COUNT(*) c FROM periods"
                              " GROUP BY lane, period_start HAVING c > 1)").fetchone()[0],
    }
    conn.close()
    return out


class _Run:
    """The service as a subprocess, its stderr collected by a thread; ``ready`` is set when it
    logs that it is ready, ``ready_at`` / ``ended_at`` are monotonic times."""

    def __init__(self, cfg: Path):
        self.proc = start("run", "--config", str(cfg))
        self.lines: list[str] = []
        self.ready = threading.Event()
        self.ready_at = self.ended_at = None
        self._t = threading.Thread(target=self._read, daemon=True)
        self._t.start()

    def _read(self) -> None:
        for line in self.proc.stderr:
            self.lines.append(line)
            if "ready:" in line and not self.ready.is_set():
                self.ready_at = time.monotonic()
                self.ready.set()
        self.ended_at = time.monotonic()

    def wait(self, timeout: float = 120) -> int:
        rc = self.proc.wait(timeout=timeout)
        self._t.join(timeout=10)
        self.proc.stdout.close()
        return rc

    @property
    def err(self) -> str:
        return "".join(self.lines)


def _run_to_end(cfg: Path) -> _Run:
    r = _Run(cfg)
    assert r.wait() == 0, r.err[-3000:]
    return r


def _kill_series(cfg: Path, kills: int, max_delay_s: float, seed: int) -> tuple[int, int]:
    """Start/SIGKILL the service `kills` times, then let it finish. A quarter of the kills land
    in start-up (random delay after spawn), the rest at a random moment of processing (random
    delay after it is ready). A run that finishes first is simply restarted: it resumes from its
    last checkpoint and is killed in the tail. Returns (kills, restarts that resumed)."""
    rng = random.Random(seed)
    done, resumed = 0, 0
    while done < kills:
        r = _Run(cfg)
        if rng.random() < 0.25:
            delay = rng.uniform(0.05, 1.0)
        else:
            r.ready.wait(60)
            delay = rng.uniform(0.0, max_delay_s)
        try:
            r.proc.wait(timeout=delay)
        except subprocess.TimeoutExpired:
            r.proc.kill()
            done += 1
        r.wait(30)
        resumed += "resuming after frame" in r.err
    r = _run_to_end(cfg)
    resumed += "resuming after frame" in r.err
    return done, resumed


def _check(tmp_path: Path, shared_data: Path, frames: int, period_s: int, kills: int, seed: int,
           kill_frac: float) -> None:
    ref_dir, kill_dir = tmp_path / "ref", tmp_path / "kill"
    ref_dir.mkdir()
    kill_dir.mkdir()
    ref_cfg = cdnet_site(ref_dir, shared_data, frames=frames, period_s=period_s)
    kill_cfg = cdnet_site(kill_dir, shared_data, frames=frames, period_s=period_s)
    clean = _run_to_end(ref_cfg)
    processing_s = clean.ended_at - clean.ready_at
    ref = _dump(ref_dir / "store.sqlite")
    complete = int((frames - 1) / FPS // period_s)  # the last period ends after the last frame
    assert len([r for r in ref["periods"] if not r[12]]) == 2 * complete  # two lanes
    assert sum(r[3] for r in ref["periods"]) > 0, "the clean run counted no vehicles"

    n, resumed = _kill_series(kill_cfg, kills, processing_s * kill_frac, seed)
    got = _dump(kill_dir / "store.sqlite")
    assert n == kills
    # at least some restarts must have resumed from a checkpoint, else resume went untested
    assert resumed >= kills // 4, f"only {resumed} of {kills} restarts resumed (seed {seed})"
    assert got["dupes"] == 0
    assert got["periods"] == ref["periods"], f"periods differ after kills (seed {seed})"
    assert got["events"] == ref["events"], f"loop events differ after kills (seed {seed})"
    assert got["vehicles"] == ref["vehicles"], f"vehicles differ after kills (seed {seed})"


def test_sigkill_restart_keeps_every_period_exactly_once(tmp_path, shared_data) -> None:
    # 200 frames (8 s) with 2 s periods: a checkpoint every 50 frames, so kills land in
    # start-up, mid-period and just after checkpoints.
    seed = random.randrange(1 << 30)
    _check(tmp_path, shared_data, frames=200, period_s=2, kills=20, seed=seed, kill_frac=1.0)


@pytest.mark.slow
@pytest.mark.timeout(3600)
def test_sigkill_many_times_on_the_whole_clip(tmp_path, shared_data) -> None:
    seed = random.randrange(1 << 30)
    # kills within a sixth of a clean run's processing time on average: many land mid-clip
    _check(tmp_path, shared_data, frames=1700, period_s=5, kills=60, seed=seed, kill_frac=1 / 3)
