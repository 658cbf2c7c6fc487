"""`roadwatch run`: the detector service from a config file, wired to the real drivers."""

from __future__ import annotations

import logging
import signal
import sys
import threading
from importlib.metadata import PackageNotFoundError, version as _pkg_version
from pathlib import Path
from typing import Callable

import click

from appliance.config import DEFAULT_CONFIG_PATH, ConfigError, SiteConfig, load_site, parse_site
from appliance.service import Service, ServiceHooks

log = logging.getLogger("roadwatch")


def software_version() -> str:
    try:
        return _pkg_version("roadwatch")
    except PackageNotFoundError:
        return "0+unknown"


def _scene_factory(preset: str, seed: int, **kw):
    from tools.simulate import SceneStream

    return SceneStream(preset, seed, **kw)


def make_hooks(site: SiteConfig) -> ServiceHooks:
    from drivers.outputs import build_outputs
    from drivers.sources import open_source
    from drivers.systemd_notify import SystemdNotifier

    def make_source(s: SiteConfig):
        base = Path(s.path).resolve().parent if s.path else Path.cwd()
        return open_source(s.source, base_dir=base, scene_factory=_scene_factory)

    return ServiceHooks(make_source=make_source, make_outputs=build_outputs, notifier=SystemdNotifier())


def with_overrides(site: SiteConfig, overrides: dict[str, dict]) -> SiteConfig:
    """The same site with some [section] keys replaced, validated again."""
    import copy

    raw = copy.deepcopy(site.raw)
    for section, values in overrides.items():
        node = raw
        for part in section.split("."):
            node = node.setdefault(part, {})
        node.update(values)
    return parse_site(raw, site.path)


def setup_logging(verbose: bool = False) -> None:
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )


def serve(site: SiteConfig, *, seconds: float | None = None, store_path: str | None = None,
          on_ready: Callable[[Service], None] | None = None) -> Service:
    """Run the service in this (main) thread with signals and the status endpoint."""
    from drivers.sources import SourceError
    from drivers.status_http import StatusServer

    service = Service(site, make_hooks(site), version=software_version(), store_path=store_path)
    status = None
    if site.status.enabled:
        try:
            status = StatusServer(site.status.host, site.status.port, service)
        except OSError as e:
            raise click.ClickException(f"status.port: cannot listen on {site.status.host}:{site.status.port} ({e.strerror})")
        status.start()
        print(f"status: http://{site.status.host}:{status.port}/api/status", flush=True)
    old = {}
    if threading.current_thread() is threading.main_thread():
        for sig, fn in ((signal.SIGTERM, lambda *a: service.stop()), (signal.SIGINT, lambda *a: service.stop()),
                        (signal.SIGHUP, lambda *a: service.request_reload())):
            old[sig] = signal.signal(sig, fn)
    watcher = None
    if on_ready is not None:
        def _watch() -> None:
            while not service.ready and not service._stop.is_set():
                service._stop.wait(0.1)
            on_ready(service)

        watcher = threading.Thread(target=_watch, daemon=True)
        watcher.start()
    try:
        service.run(max_seconds=seconds)
    except (SourceError, ConfigError) as e:
        raise click.ClickException(str(e))
    except RuntimeError as e:
        if "outputs." in str(e) or "source" in str(e):
            raise click.ClickException(str(e))
        raise
    finally:
        service.stop()
        if status is not None:
            status.stop()
        for sig, fn in old.items():
            signal.signal(sig, fn)
    return service


@click.command("run")
@click.option("--config", "config_path", default=DEFAULT_CONFIG_PATH, show_default=True,
              type=click.Path(dir_okay=False), help="Site configuration (TOML).")
@click.option("--seconds", type=float, default=None, help="Stop after this many seconds (default: run until SIGTERM).")
@click.option("--store", "store_path", default=None, help="SQLite file (default: store.path, relative to the config).")
@click.option("-v", "--verbose", is_flag=True, help="Debug logging.")
def run(config_path: str, seconds: float | None, store_path: str | None, verbose: bool) -> None:
    """Run the detector service: camera → tracker → measures → store and controller outputs.

    Runs until SIGTERM/Ctrl-C (the partial period is written); SIGHUP reloads the config.
    """
    setup_logging(verbose)
    try:
        site = load_site(config_path)
    except ConfigError as e:
        click.echo(f"roadwatch: invalid configuration: {e}", err=True)
        sys.exit(2)
    serve(site, seconds=seconds, store_path=store_path)
