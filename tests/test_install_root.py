"""`roadwatch install/uninstall --root` into a staging tree, and the unit checked by systemd-analyze."""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile

import pytest

from appliance.config import load_site
from test_service_sitefiles import REPO, cli, env


def _rw(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(cli(*args), cwd=REPO, env=env(), capture_output=True, text=True, timeout=60)


def test_install_and_uninstall_in_a_staging_root(tmp_path) -> None:
    root = tmp_path / "root"
    r = _rw("install", "--root", str(root))
    assert r.returncode == 0, r.stderr
    cfg = root / "etc/roadwatch/config.toml"
    unit = root / "etc/systemd/system/roadwatch.service"
    assert load_site(cfg).site.name  # the example config is valid
    assert (root / "var/lib/roadwatch").is_dir() and (root / "var/cache/roadwatch/numba").is_dir()
    assert (root / "etc/systemd/system/multi-user.target.wants/roadwatch.service").is_symlink()
    text = unit.read_text()
    for line in ("Type=notify", "WatchdogSec=", "Restart=on-failure", "User=roadwatch", "ProtectSystem=strict",
                 "StateDirectory=roadwatch", "CacheDirectory=roadwatch", "ConfigurationDirectory=roadwatch",
                 "Environment=NUMBA_CACHE_DIR=/var/cache/roadwatch/numba", "DevicePolicy=closed"):
        assert line in text, line
    assert "ExecStart=/usr/local/bin/roadwatch" not in text or shutil.which("roadwatch") is None

    cfg.write_text(cfg.read_text().replace("Example St northbound", "Edited site"))
    assert _rw("install", "--root", str(root)).returncode == 0
    assert "Edited site" in cfg.read_text()  # never overwritten

    r = _rw("uninstall", "--root", str(root))
    assert r.returncode == 0, r.stderr
    assert not unit.exists() and cfg.exists() and (root / "var/lib/roadwatch").is_dir()
    r = _rw("uninstall", "--root", str(root), "--purge")
    assert r.returncode == 0 and not cfg.exists() and not (root / "var/lib/roadwatch").exists()


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze is not installed")
def test_installed_unit_passes_systemd_analyze_verify(tmp_path) -> None:
    root = tmp_path / "root"
    assert _rw("install", "--root", str(root)).returncode == 0
    unit = root / "etc/systemd/system/roadwatch.service"
    r = subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert "roadwatch.service" not in r.stderr, r.stderr  # no warnings about our unit
    # the check can fail: a broken unit is reported
    bad = tmp_path / "bad" / "roadwatch.service"
    bad.parent.mkdir()
    bad.write_text(unit.read_text().replace("Type=notify", "Type=notifyy"))
    r = subprocess.run(["systemd-analyze", "verify", str(bad)], capture_output=True, text=True, timeout=60)
    assert r.returncode != 0 or "roadwatch.service" in r.stderr


def test_install_on_the_live_system_needs_root_or_a_staging_root(tmp_path) -> None:
    import os

    if os.geteuid() == 0:
        pytest.skip("running as root: the live install path would touch this machine")
    r = _rw("install")
    assert r.returncode != 0 and "run as root" in r.stderr


def test_install_works_from_a_built_wheel(tmp_path) -> None:
    # a non-editable install has no repo beside it: the example config and the unit must travel in the wheel
    # (the build is isolated like the README's pip install, so it needs the same access to setuptools>=68)
    src = tmp_path / "src"
    for name in ("appliance", "drivers", "tools", "config", "systemd"):
        shutil.copytree(REPO / name, src / name, symlinks=True, ignore=shutil.ignore_patterns("__pycache__"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(REPO / name, src / name)
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q",
                        "-w", str(tmp_path / "whl"), str(src)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    (wheel,) = (tmp_path / "whl").glob("roadwatch-*.whl")
    site = tmp_path / "site"
    with zipfile.ZipFile(wheel) as z:
        z.extractall(site)
    assert not (site / "tools" / "data" / "example.toml").is_symlink()
    wheel_env = {**env(), "PYTHONPATH": str(site)}
    r = subprocess.run([sys.executable, "-c", "import tools.install; print(tools.install.__file__)"],
                       cwd=tmp_path, env=wheel_env, capture_output=True, text=True, timeout=60)
    assert r.stdout.strip() == str(site / "tools" / "install.py"), r.stdout + r.stderr  # not the repo's copy
    root = tmp_path / "root"
    r = subprocess.run([sys.executable, "-m", "tools.cli", "install", "--root", str(root), "--exec", "/usr/bin/rw"],
                       cwd=tmp_path, env=wheel_env, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert (root / "etc/roadwatch/config.toml").read_text() == (REPO / "config/example.toml").read_text()
    unit = (root / "etc/systemd/system/roadwatch.service").read_text()
    assert "ExecStart=/usr/bin/rw" in unit
    assert unit == (REPO / "systemd/roadwatch.service").read_text().replace("/usr/local/bin/roadwatch", "/usr/bin/rw")
