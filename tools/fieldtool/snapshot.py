"""`roadwatch snapshot`: grab a frame from the configured source or a running service to a PNG."""

from __future__ import annotations

import dataclasses
import importlib
import logging
import threading
from pathlib import Path
from typing import Callable

import click
import cv2
import numpy as np

from appliance.config import ConfigError, SiteConfig, load_site
from tools.fieldtool.common import config_option, service_url, source_only_config, url_option, write_file, write_png
from tools.fieldtool.overlay import blank, draw_site
from tools.fieldtool.statusclient import ServiceError, ServiceUnreachable, StatusClient


class SnapshotError(Exception):
    """No frame could be read from the source."""


def _resolve(url: str, cfg: SiteConfig) -> str:
    """A relative file source is taken relative to the config file's directory."""
    if "://" in url or url.startswith(("synthetic:", "/")):
        return url
    prefix = ""
    if url.startswith("images:"):
        prefix, url = "images:", url[len("images:"):]
    if cfg.path and not Path(url).exists():
        cand = Path(cfg.path).parent / url
        if cand.exists() or cand.parent.is_dir():
            url = str(cand)
    return prefix + url


def _scene_factory():
    try:
        return getattr(importlib.import_module("tools.simulate"), "SceneStream")
    except (ImportError, AttributeError):
        return None


def grab_frame(cfg: SiteConfig, skip: int = 0) -> np.ndarray:
    """One frame (after skipping ``skip`` frames) from the configured source, as an image array.

    Files are read as fast as possible; a live source gets open_timeout_s + read_timeout_s.
    """
    try:
        from drivers.sources import SourceError, open_source
    except ImportError:
        return _grab_cv2(cfg, skip)
    base = Path(cfg.path).parent if cfg.path else None
    source_cfg = dataclasses.replace(cfg.source, realtime=False, loop=False)
    try:
        src = open_source(source_cfg, base, _scene_factory())
    except SourceError as e:
        raise SnapshotError(str(e)) from None
    result: dict = {}

    def run() -> None:
        try:
            src.open()
            frame = None
            for _ in range(skip + 1):
                frame = src.read()
                if frame is None:
                    break
            result["frame"] = frame
        except Exception as e:  # any driver failure is a failed grab for the installer
            result["error"] = e

    # the driver logs each reconnect attempt; keep the last message for the error instead
    messages: list[str] = []
    handler = logging.Handler()
    handler.emit = lambda record: messages.append(record.getMessage())  # type: ignore[method-assign]
    driver_log = logging.getLogger("roadwatch.source")
    old_propagate = driver_log.propagate
    driver_log.addHandler(handler)
    driver_log.propagate = False
    th = threading.Thread(target=run, daemon=True)
    try:
        th.start()
        th.join(cfg.source.open_timeout_s + cfg.source.read_timeout_s + 0.05 * skip)
        try:
            src.close()
        except Exception:
            pass
    finally:
        driver_log.removeHandler(handler)
        driver_log.propagate = old_propagate
    if th.is_alive():
        last = f" (last: {messages[-1]})" if messages else ""
        raise SnapshotError(f"source {cfg.source.url!r}: no frame within "
                            f"{cfg.source.open_timeout_s + cfg.source.read_timeout_s:.0f} s{last}")
    if "error" in result:
        raise SnapshotError(f"source {cfg.source.url!r}: {result['error']}")
    if result.get("frame") is None:
        raise SnapshotError(f"source {cfg.source.url!r} gave no frame")
    return result["frame"].image


def _grab_cv2(cfg: SiteConfig, skip: int) -> np.ndarray:
    url = _resolve(cfg.source.url, cfg)
    if url.startswith("synthetic:"):
        raise SnapshotError(f"source {url!r} needs drivers.sources, which is not available in this build")
    cap = cv2.VideoCapture(url.removeprefix("images:"))
    try:
        if not cap.isOpened():
            raise SnapshotError(f"source {cfg.source.url!r} cannot be opened")
        img = None
        for _ in range(skip + 1):
            ok, img = cap.read()
            if not ok:
                raise SnapshotError(f"source {cfg.source.url!r} gave no frame")
        return img
    finally:
        cap.release()


def base_image(cfg: SiteConfig, snapshot: str | None, warn: Callable[[str], object] = click.echo) -> np.ndarray:
    """The picture to draw on: a snapshot file, else a frame from the source, else flat grey."""
    if snapshot:
        img = cv2.imread(snapshot, cv2.IMREAD_COLOR)
        if img is None:
            raise click.ClickException(f"{snapshot}: not a readable image")
        if img.shape[1] != cfg.source.width or img.shape[0] != cfg.source.height:
            raise click.ClickException(
                f"{snapshot}: is {img.shape[1]}x{img.shape[0]} but the config's source is "
                f"{cfg.source.width}x{cfg.source.height}; take a new snapshot"
            )
        return img
    try:
        img = grab_frame(cfg)
        if img.shape[1] == cfg.source.width and img.shape[0] == cfg.source.height:
            return img
        warn(f"warning: the source gives {img.shape[1]}x{img.shape[0]}, the config says "
             f"{cfg.source.width}x{cfg.source.height}; drawing on a blank image", err=True)
    except SnapshotError as e:
        warn(f"warning: {e}; drawing on a blank image (use --snapshot PNG)", err=True)
    return blank(cfg.source.width, cfg.source.height)


@click.command("snapshot")
@config_option
@click.option("--out", "-o", type=click.Path(dir_okay=False), default="snapshot.png", show_default=True,
              help="PNG file to write.")
@click.option("--from-service", is_flag=True, help="Ask the running service for its latest frame.")
@url_option
@click.option("--overlay/--no-overlay", default=False, show_default=True,
              help="Draw lanes, zones, loops and fiducials on it.")
@click.option("--skip", type=click.IntRange(min=0), default=0, show_default=True,
              help="Frames to skip first (files: pick a later frame).")
def snapshot(config_path: str, out: str, from_service: bool, url: str | None, overlay: bool, skip: int) -> None:
    """Grab one frame to a PNG, from the configured source or the running service.

    \b
    Examples:
      roadwatch snapshot -c /etc/roadwatch/config.toml -o snap.png
      roadwatch snapshot --from-service --overlay -o live.png
    """
    if from_service:
        client = StatusClient(service_url(url, config_path))
        try:
            png = client.snapshot_png(overlay=overlay)
        except (ServiceError, ServiceUnreachable) as e:
            raise click.ClickException(f"snapshot from the service failed: {e}") from None
        write_file(out, png)
        click.echo(f"wrote {out} ({len(png)} bytes) from {client.url}")
        return
    try:
        cfg = load_site(config_path)
    except ConfigError as e:
        if overlay or e.key == "file":
            raise click.ClickException(f"invalid config: {e}") from None
        cfg = source_only_config(config_path)  # not calibrated yet: the source is enough
    click.echo(f"reading a frame from {cfg.source.url} ...", err=True)
    try:
        img = grab_frame(cfg, skip)
    except SnapshotError as e:
        raise click.ClickException(str(e)) from None
    if overlay:
        img = draw_site(img, cfg)
    write_png(out, img)
    click.echo(f"wrote {out} ({img.shape[1]}x{img.shape[0]})")
