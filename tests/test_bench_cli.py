"""`roadwatch bench` end to end on a short scene: it renders the scene once, times every stage and reports
them (the numbers are the command's to report, not the test's to judge)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

from tools.bench import STAGES


def _bench(tmp_path, *args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, TMPDIR=str(tmp_path))  # the scene cache goes under the temp directory
    return subprocess.run([sys.executable, "-m", "tools.cli", "bench", *args], capture_output=True, text=True,
                          env=env, timeout=600)


def test_bench_renders_once_and_reports_every_stage(tmp_path):
    out = tmp_path / "bench.json"
    args = ("--seconds", "4", "--size", "640x480", "--preset", "dense", "--no-compile", "--json", str(out))
    r = _bench(tmp_path, *args)
    assert r.returncode == 0, r.stderr
    assert "rendering dense 640x480" in r.stderr
    assert (tmp_path / "roadwatch-bench" / "dense-s1-640x480-4s" / "video.mp4").is_file()
    res = json.loads(out.read_text())
    (run,) = res["runs"]
    assert run["frames"] == 100 and run["mean_features"] > 0
    assert all(run[f"{s}_fps"] > 0 for s in STAGES) and run["pipeline_fps"] > 0 and run["decode_fps"] > 0
    assert run["cost_vs_decode"] == run["decode_fps"] / run["pipeline_fps"]
    assert res["peak_rss_mb"] > 0
    assert "x decode" in r.stdout and "peak RSS" in r.stdout
    again = _bench(tmp_path, *args)  # the cached scene is used: no second rendering
    assert again.returncode == 0 and "rendering" not in again.stderr


def test_bench_names_a_core_it_may_not_use(tmp_path):
    r = _bench(tmp_path, "--core", "4096", "--seconds", "1")
    assert r.returncode == 2 and "core 4096 is not available" in r.stderr
