"""`roadwatch selftest` as the installer runs it: render, real pipeline, store and Modbus, checked
against the scene's truth; and it reports FAIL (exit 1) when a check cannot pass."""

from __future__ import annotations

import subprocess

from test_service_sitefiles import REPO, cli, env


def test_selftest_passes_on_this_box(tmp_path) -> None:
    r = subprocess.run(cli("selftest", "--seconds", "12", "--workdir", str(tmp_path)), cwd=REPO, env=env(),
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr[-3000:]
    assert "selftest PASSED" in r.stdout
    for check in ("store: every complete period written once", "lane 1 count vs truth",
                  "modbus: period sequence and channel counts", "health:"):
        assert f"[PASS] {check}" in r.stdout, r.stdout
    assert (tmp_path / "selftest.sqlite").is_file() and (tmp_path / "scene" / "truth").is_dir()


def test_selftest_reports_failure(tmp_path) -> None:
    r = subprocess.run(cli("selftest", "--preset", "no-such-preset", "--seconds", "2", "--workdir", str(tmp_path)),
                       cwd=REPO, env=env(), capture_output=True, text=True, timeout=300)
    assert r.returncode == 1
    assert "[FAIL] selftest ran" in r.stdout and "no-such-preset" in r.stdout
