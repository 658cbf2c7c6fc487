"""Helpers for the service tests: site files in tmp for the real cdnet-highway clip, running the
real `roadwatch` CLI as a subprocess, and polling its status endpoint."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import tomli_w

from appliance.config import load_site

REPO = Path(__file__).resolve().parent.parent
CLIP = "cdnet-highway"


def link_frames(shared_data: Path, dest: Path, n: int) -> Path:
    """Symlink the first n frames of the real clip into dest (never copied)."""
    dest.mkdir(parents=True, exist_ok=True)
    src = shared_data / CLIP / "input"
    for i in range(1, n + 1):
        name = f"in{i:06d}.jpg"
        if not (dest / name).exists():
            (dest / name).symlink_to(src / name)
    return dest


def cdnet_site(tmp_path: Path, shared_data: Path, *, frames: int | None = 300, period_s: int = 2,
               url: str | None = None, name: str = "site.toml", **sections: dict) -> Path:
    """A site file in tmp_path for the real clip (calibration, lanes, loops from its hand counts)."""
    from tools.handcount import load_counts, site_dict_from_counts

    cfg_path = tmp_path / name
    counts_path = shared_data / CLIP / "counts.json"
    site = site_dict_from_counts(load_counts(counts_path), counts_path, cfg_path)
    if url is None:
        if frames is None:
            url = "images:" + os.path.relpath(shared_data / CLIP / "input", tmp_path) + "/in%06d.jpg"
        else:
            link_frames(shared_data, tmp_path / "frames", frames)
            url = "images:frames/in%06d.jpg"
    site["source"]["url"] = url
    site["measures"] = {"period_s": period_s}
    site["store"] = {"path": "store.sqlite"}
    site["status"] = {"enabled": False}
    for key, values in sections.items():
        site.setdefault(key, {}).update(values)
    cfg_path.write_text(tomli_w.dumps(site))
    return cfg_path


def cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "tools.cli", *args]


def env() -> dict:
    e = dict(os.environ)
    e.setdefault("PYTHONUNBUFFERED", "1")
    return e


def start(*args: str, **kw) -> subprocess.Popen:
    return subprocess.Popen(cli(*args), cwd=REPO, env=kw.pop("env", env()), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, **kw)


def get(port: int, path: str, timeout: float = 5.0) -> tuple[int, bytes]:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=timeout) as r:
            return r.status, r.read()
    except urllib.error.HTTPError as e:
        return e.code, e.read()


def post(port: int, path: str, body: dict, timeout: float = 30.0) -> tuple[int, dict]:
    req = urllib.request.Request(f"http://127.0.0.1:{port}{path}", data=json.dumps(body).encode(),
                                 headers={"Content-Type": "application/json"}, method="POST")
    try:
        with urllib.request.urlopen(req, timeout=timeout) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read())


def wait_status(port: int, proc: subprocess.Popen, until=lambda s: s.get("ready"), timeout: float = 60.0) -> dict:
    """Poll /api/status until ``until(status)``; fails if the process exits first."""
    deadline = time.monotonic() + timeout
    last = None
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise AssertionError(f"service exited {proc.returncode}: {proc.stderr.read()[-3000:]}")
        try:
            code, body = get(port, "/api/status", timeout=2)
            if code == 200:
                last = json.loads(body)
                if until(last):
                    return last
        except (OSError, ValueError):
            pass
        time.sleep(0.1)
    raise AssertionError(f"status condition not reached in {timeout} s; last status {last}")


def test_cdnet_site_file_is_valid(tmp_path, shared_data) -> None:
    path = cdnet_site(tmp_path, shared_data, frames=5, period_s=10)
    site = load_site(path)
    assert site.measures.period_s == 10 and len(site.lanes) == 2 and len(site.loops) == 2
    assert (tmp_path / "frames" / "in000005.jpg").resolve().is_file()
