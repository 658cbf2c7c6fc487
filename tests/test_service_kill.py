"""The service as a real subprocess on the real clip, SIGKILLed at random moments and restarted:
every completed period ends up in the store exactly once, identical to a run without kills."""

from __future__ import annotations

import random
import sqlite3
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


def _run_to_end(cfg: Path, timeout: float = 120) -> str:
    p = start("run", "--config", str(cfg))
    _, err = p.communicate(timeout=timeout)
    assert p.returncode == 0, err[-3000:]
    return err


def _kill_series(cfg: Path, kills: int, window: tuple[float, float], seed: int) -> tuple[int, int]:
    """Start/SIGKILL the service `kills` times, then let it finish. Returns (kills, resumes seen)."""
    rng = random.Random(seed)
    done, resumed = 0, 0
    while done < kills:
        p = start("run", "--config", str(cfg))
        time.sleep(rng.uniform(*window))
        if p.poll() is None:
            p.kill()
            done += 1
        _, err = p.communicate(timeout=30)
        resumed += "resuming after frame" in err
        if p.returncode == 0:  # it finished before the kill: start over from an empty store
            for f in cfg.parent.glob("store.sqlite*"):
                f.unlink()
    err = _run_to_end(cfg)
    resumed += "resuming after frame" in err
    return done, resumed


def _check(tmp_path: Path, shared_data: Path, frames: int, period_s: int, kills: int,
           window: tuple[float, float], seed: int) -> None:
    ref_dir, kill_dir = tmp_path / "ref", tmp_path / "kill"
    ref_dir.mkdir()
    kill_dir.mkdir()
    ref_cfg = cdnet_site(ref_dir, shared_data, frames=frames, period_s=period_s)
    kill_cfg = cdnet_site(kill_dir, shared_data, frames=frames, period_s=period_s)
    _run_to_end(ref_cfg)
    ref = _dump(ref_dir / "store.sqlite")
    complete = int((frames - 1) / FPS // period_s)  # the last period ends after the last frame
    assert len([r for r in ref["periods"] if not r[12]]) == 2 * complete  # two lanes
    assert sum(r[3] for r in ref["periods"]) > 0, "the clean run counted no vehicles"

    n, resumed = _kill_series(kill_cfg, kills, window, seed)
    got = _dump(kill_dir / "store.sqlite")
    assert n == kills
    # at least some restarts must have resumed from a checkpoint, else resume went untested
    assert resumed >= kills // 4, f"only {resumed} of {kills} restarts resumed (seed {seed})"
    assert got["dupes"] == 0
    assert got["periods"] == ref["periods"], f"periods differ after kills (seed {seed})"
    assert got["events"] == ref["events"], f"loop events differ after kills (seed {seed})"
    assert got["vehicles"] == ref["vehicles"], f"vehicles differ after kills (seed {seed})"


def test_sigkill_restart_keeps_every_period_exactly_once(tmp_path, shared_data) -> None:
    # 300 frames (12 s) with 2 s periods: a checkpoint every ~0.5 s of processing, so kills
    # between 0.3 and 3 s after start land before start-up, mid-period and after checkpoints.
    seed = random.randrange(1 << 30)
    _check(tmp_path, shared_data, frames=300, period_s=2, kills=20, window=(0.3, 3.0), seed=seed)


@pytest.mark.slow
def test_sigkill_many_times_on_the_whole_clip(tmp_path, shared_data) -> None:
    seed = random.randrange(1 << 30)
    _check(tmp_path, shared_data, frames=1700, period_s=5, kills=60, window=(0.3, 6.0), seed=seed)
