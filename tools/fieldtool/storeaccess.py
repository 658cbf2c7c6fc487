"""Opening the service's SQLite store read-only for exports and reports."""

from __future__ import annotations

import tomllib
from pathlib import Path

import click

from appliance.store import Store, StoreError


def store_path(db: str | None, config_path: str) -> Path:
    """--db if given, else the config's store.path (relative to the config file's directory)."""
    if db:
        return Path(db)
    p = Path(config_path)
    try:
        raw = tomllib.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise click.ClickException(f"{p}: no config file; give --db PATH or --config") from None
    except (OSError, tomllib.TOMLDecodeError) as e:
        raise click.ClickException(f"{p}: cannot be read ({e})") from None
    rel = Path(raw.get("store", {}).get("path", "roadwatch.sqlite"))
    return rel if rel.is_absolute() else p.parent / rel


def open_readonly(path: Path) -> Store:
    try:
        return Store(path, readonly=True)
    except StoreError as e:
        raise click.ClickException(str(e)) from None
