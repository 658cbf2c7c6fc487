"""Helpers shared by the field tool commands: config loading, atomic writes, dates, service URL."""

from __future__ import annotations

import os
import tempfile
import tomllib
from datetime import datetime, timezone
from pathlib import Path

import click
import numpy as np

from appliance.config import DEFAULT_CONFIG_PATH, ConfigError, SiteConfig, SourceConfig, load_site, parse_site

CONFIG_ENV = "ROADWATCH_CONFIG"

config_option = click.option(
    "--config",
    "-c",
    "config_path",
    type=click.Path(dir_okay=False),
    default=DEFAULT_CONFIG_PATH,
    envvar=CONFIG_ENV,
    show_default=True,
    help=f"Site config file (or ${CONFIG_ENV}).",
)

url_option = click.option(
    "--url",
    default=None,
    metavar="URL",
    help="Status API of the running service (default: from the config's [status], else http://127.0.0.1:8765).",
)


def load_config(path: str | Path) -> SiteConfig:
    """Load and validate a site config; a problem becomes a ClickException naming the key."""
    try:
        return load_site(path)
    except ConfigError as e:
        raise click.ClickException(f"invalid config: {e}") from None


def read_toml(path: str | Path) -> dict:
    """The raw TOML table of a file (no validation), with clear errors."""
    p = Path(path)
    try:
        return tomllib.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise click.ClickException(f"{p}: file does not exist") from None
    except OSError as e:
        raise click.ClickException(f"{p}: cannot be read ({e.strerror})") from None
    except tomllib.TOMLDecodeError as e:
        raise click.ClickException(f"{p}: not valid TOML ({e})") from None


def validate_dict(data: dict, source: str) -> SiteConfig:
    """parse_site with a ClickException on error."""
    try:
        return parse_site(data, source)
    except ConfigError as e:
        raise click.ClickException(f"invalid config: {e}") from None


def atomic_write(path: str | Path, data: bytes | str) -> None:
    """Write a file so that readers see the old or the new content, never a part of it.

    Temp file in the same directory, fsync, os.replace, fsync of the directory.
    """
    p = Path(path)
    if isinstance(data, str):
        data = data.encode("utf-8")
    d = p.parent if str(p.parent) else Path(".")
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=d)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        if p.exists():
            os.chmod(tmp, p.stat().st_mode & 0o777)
        else:
            os.chmod(tmp, 0o644)
        os.replace(tmp, p)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    dfd = os.open(d, os.O_RDONLY)
    try:
        os.fsync(dfd)
    finally:
        os.close(dfd)


def write_png(path: str | Path, image: np.ndarray) -> None:
    """Encode an image as PNG and write it atomically."""
    import cv2

    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise click.ClickException(f"{path}: could not encode the PNG")
    write_file(path, buf.tobytes())


def write_file(path: str | Path, data: bytes | str) -> None:
    """atomic_write with OS errors turned into a ClickException naming the file."""
    try:
        atomic_write(path, data)
    except OSError as e:
        raise click.ClickException(f"{path}: cannot write ({e.strerror or e})") from None


def parse_when(text: str) -> float:
    """ISO 8601 (naive = UTC) or Unix seconds -> Unix seconds."""
    s = text.strip()
    try:
        return float(s)
    except ValueError:
        pass
    try:
        dt = datetime.fromisoformat(s.replace("Z", "+00:00"))
    except ValueError:
        raise click.BadParameter(
            f"{text!r} is neither ISO 8601 (e.g. 2026-01-01T08:00:00Z) nor Unix seconds"
        ) from None
    if dt.tzinfo is None:
        dt = dt.replace(tzinfo=timezone.utc)
    return dt.timestamp()


class When(click.ParamType):
    name = "TIME"

    def convert(self, value: str | float, param: click.Parameter | None, ctx: click.Context | None) -> float:
        if isinstance(value, float):
            return value
        try:
            return parse_when(str(value))
        except click.BadParameter as e:
            self.fail(e.message, param, ctx)


def iso(wall: float) -> str:
    return datetime.fromtimestamp(wall, timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


def service_url(url: str | None, config_path: str | None) -> str:
    """--url if given, else the config's [status] host/port, else the default."""
    if url:
        return url.rstrip("/")
    host, port = "127.0.0.1", 8765
    if config_path and Path(config_path).is_file():
        try:
            st = tomllib.loads(Path(config_path).read_text(encoding="utf-8")).get("status", {})
            host, port = st.get("host", host), int(st.get("port", port))
        except (OSError, tomllib.TOMLDecodeError, ValueError, TypeError) as e:
            click.echo(f"warning: {config_path}: cannot read [status] ({e}); trying {host}:{port}", err=True)
    if host in ("0.0.0.0", "", "::"):
        host = "127.0.0.1"
    return f"http://{host}:{port}"


def parse_xy(text: str, what: str = "point") -> tuple[float, float]:
    """'x,y' -> (x, y)."""
    try:
        a, b = text.split(",")
        return float(a), float(b)
    except ValueError:
        raise click.BadParameter(f"{what} {text!r}: expected 'x,y' (two numbers)") from None


def parse_polygon(text: str, what: str = "polygon") -> list[list[float]]:
    """'x,y x,y x,y ...' (spaces or ';' between points) -> [[x, y], ...]."""
    parts = [p for p in text.replace(";", " ").split() if p]
    pts = [list(parse_xy(p, f"{what} point")) for p in parts]
    if len(pts) < 3:
        raise click.BadParameter(f"{what}: needs at least 3 points 'x,y x,y x,y', got {len(pts)}")
    return pts


def source_only_config(path: str | Path) -> SiteConfig:
    """A SiteConfig with just the file's [source] section: enough to grab a frame from a site
    that is not calibrated yet (the full config would not validate)."""
    raw = read_toml(path)
    src = raw.get("source", {})
    if not isinstance(src, dict):
        raise click.ClickException(f"{path}: source: expected a table")
    try:
        cfg = SiteConfig(source=SourceConfig(**src))
    except TypeError as e:
        raise click.ClickException(f"{path}: bad [source] section ({e})") from None
    cfg.path = str(path)
    return cfg
