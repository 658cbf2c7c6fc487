"""Memory stays flat over a long run: the service on the synthetic source processed as fast as
possible (30 simulated minutes in the slow test), RSS sampled from /proc while it runs."""

from __future__ import annotations

import json
import signal
from pathlib import Path

import pytest
import tomli_w

from test_service_sitefiles import start, wait_status


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    raise AssertionError("no VmRSS")


def run_and_sample(tmp_path: Path, port: int, sim_minutes: float, samples: int = 12) -> list[tuple[float, float]]:
    """Returns [(simulated minutes, RSS MB)] sampled while the service runs."""
    from tools.simulate import site_config_dict

    site = site_config_dict("free-flow", 2, width=320, height=240,
                            url="synthetic:free-flow?seed=2&realtime=0")
    site["measures"] = {"period_s": 60}
    site["store"] = {"path": "mem.sqlite"}
    site["status"] = {"enabled": True, "port": port}
    site.setdefault("outputs", {})
    cfg = tmp_path / "site.toml"
    cfg.write_text(tomli_w.dumps(site))
    proc = start("run", "--config", str(cfg))
    out = []
    try:
        total = int(sim_minutes * 60 * 25)
        for k in range(1, samples + 1):
            st = wait_status(port, proc, lambda s, n=total * k // samples: s["frames"] >= n, timeout=3600)
            out.append((st["frames"] / 25 / 60, rss_mb(proc.pid)))
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    return out


def test_memory_flat_over_a_short_run(tmp_path, port) -> None:
    # the fast variant: catches gross per-frame leaks only (a frame kept per step is 77 kB,
    # 600 steps between the samples = 46 MB), not slow ones.
    s = run_and_sample(tmp_path, port, sim_minutes=0.6, samples=3)
    growth = s[-1][1] - s[0][1]
    assert growth < 40, f"RSS grew {growth:.0f} MB in 36 simulated seconds: {s}"


@pytest.mark.slow
@pytest.mark.timeout(3600)
def test_memory_flat_over_thirty_simulated_minutes(tmp_path, port) -> None:
    s = run_and_sample(tmp_path, port, sim_minutes=30, samples=12)
    print("simulated min, RSS MB:", json.dumps([(round(m, 1), round(r, 1)) for m, r in s]))
    # after warm-up (first quarter) RSS may move by allocator noise, never by a leak's slope
    growth = s[-1][1] - s[2][1]
    assert growth < 30, f"RSS grew {growth:.0f} MB from {s[2][0]:.0f} to {s[-1][0]:.0f} simulated min: {s}"
