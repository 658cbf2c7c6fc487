"""`roadwatch install` / `roadwatch uninstall`: the systemd unit, the config and the state and
cache directories on a roadside box (or under --root DIR for a staging tree)."""

from __future__ import annotations

import os
import pwd
import shutil
import subprocess
from pathlib import Path

import click

# config/example.toml and systemd/roadwatch.service ship as package data of `tools` (tools/data holds
# symlinks to them in the repo, real copies in a wheel), so install works from any kind of install
ASSETS = Path(__file__).resolve().parent / "data"
UNIT_NAME = "roadwatch.service"
SERVICE_USER = "roadwatch"
DEFAULT_EXEC = "/usr/local/bin/roadwatch"


def _asset(name: str) -> Path:
    p = ASSETS / name
    if not p.is_file():
        raise click.ClickException(f"{name} is missing from this installation ({p}); reinstall roadwatch")
    return p


def _under(root: Path, path: str) -> Path:
    return root / path.lstrip("/")


def _executable() -> str:
    exe = shutil.which("roadwatch")
    if exe:
        return os.path.realpath(exe) if "/shims/" in exe else exe
    return DEFAULT_EXEC


def unit_text(executable: str) -> str:
    """The unit file with ExecStart pointing at this box's roadwatch executable."""
    return _asset(UNIT_NAME).read_text().replace(DEFAULT_EXEC, executable)


def _run(cmd: list[str]) -> None:
    click.echo("  $ " + " ".join(cmd))
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        raise click.ClickException(f"{' '.join(cmd)} failed: {r.stderr.strip() or r.stdout.strip()}")


@click.command("install")
@click.option("--root", type=click.Path(file_okay=False), default=None,
              help="Install into this staging root instead of the live system (for tests and images).")
@click.option("--enable/--no-enable", default=True, show_default=True, help="Enable the unit at boot.")
@click.option("--exec", "executable", default=None, help="Path of the roadwatch executable for ExecStart.")
def install(root: str | None, enable: bool, executable: str | None) -> None:
    """Install the service: config (never overwritten), state/cache dirs, systemd unit."""
    live = root is None
    base = Path(root or "/")
    if live and os.geteuid() != 0:
        raise click.ClickException("run as root (or use --root DIR for a staging tree)")
    exe = executable or _executable()
    etc = _under(base, "/etc/roadwatch")
    state = _under(base, "/var/lib/roadwatch")
    cache = _under(base, "/var/cache/roadwatch/numba")
    unit_dir = _under(base, "/etc/systemd/system")
    for d in (etc, state, cache, unit_dir):
        d.mkdir(parents=True, exist_ok=True)
    cfg = etc / "config.toml"
    if cfg.exists():
        click.echo(f"kept existing {cfg}")
    else:
        shutil.copyfile(_asset("example.toml"), cfg)
        click.echo(f"wrote {cfg} from the example (edit it for this site)")
    unit = unit_dir / UNIT_NAME
    unit.write_text(unit_text(exe))
    click.echo(f"wrote {unit} (ExecStart {exe})")
    if live:
        try:
            pwd.getpwnam(SERVICE_USER)
        except KeyError:
            _run(["useradd", "--system", "--no-create-home", "--home-dir", "/var/lib/roadwatch",
                  "--shell", "/usr/sbin/nologin", "--groups", "video,dialout", SERVICE_USER])
        for d in (state, cache.parent, cache):
            shutil.chown(d, SERVICE_USER, SERVICE_USER)
        _run(["systemctl", "daemon-reload"])
        if enable:
            _run(["systemctl", "enable", UNIT_NAME])
        click.echo("installed; start with: systemctl start roadwatch")
    else:
        if enable:
            wants = unit_dir / "multi-user.target.wants"
            wants.mkdir(exist_ok=True)
            link = wants / UNIT_NAME
            if link.is_symlink() or link.exists():
                link.unlink()
            link.symlink_to(f"/etc/systemd/system/{UNIT_NAME}")
        click.echo(f"installed into staging root {base} (no user created, systemd not touched)")


@click.command("uninstall")
@click.option("--root", type=click.Path(file_okay=False), default=None, help="Staging root used at install.")
@click.option("--purge", is_flag=True, help="Also delete the config and the stored data.")
def uninstall(root: str | None, purge: bool) -> None:
    """Remove the service; keeps /etc/roadwatch and /var/lib/roadwatch unless --purge."""
    live = root is None
    base = Path(root or "/")
    if live and os.geteuid() != 0:
        raise click.ClickException("run as root (or use --root DIR for a staging tree)")
    unit_dir = _under(base, "/etc/systemd/system")
    if live and (unit_dir / UNIT_NAME).exists():
        subprocess.run(["systemctl", "disable", "--now", UNIT_NAME], capture_output=True)
    link = unit_dir / "multi-user.target.wants" / UNIT_NAME
    if link.is_symlink() or link.exists():
        link.unlink()
    if (unit_dir / UNIT_NAME).exists():
        (unit_dir / UNIT_NAME).unlink()
        click.echo(f"removed {unit_dir / UNIT_NAME}")
    if live:
        subprocess.run(["systemctl", "daemon-reload"], capture_output=True)
    shutil.rmtree(_under(base, "/var/cache/roadwatch"), ignore_errors=True)
    if purge:
        for d in ("/etc/roadwatch", "/var/lib/roadwatch"):
            shutil.rmtree(_under(base, d), ignore_errors=True)
            click.echo(f"purged {_under(base, d)}")
    else:
        click.echo(f"kept {_under(base, '/etc/roadwatch')} and {_under(base, '/var/lib/roadwatch')} (use --purge to delete)")
    if live:
        click.echo("the 'roadwatch' system user is kept (userdel roadwatch to remove it)")
