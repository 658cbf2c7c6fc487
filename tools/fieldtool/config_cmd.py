"""`roadwatch config validate | show | diff | apply`: check and safely install site configs."""

from __future__ import annotations

import difflib
import json
import os
import shutil
import tomllib
from dataclasses import dataclass
from pathlib import Path

import click
import tomli_w

from appliance.config import ConfigError, parse_site, to_dict
from tools.fieldtool.common import atomic_write, config_option, load_config, read_toml, service_url, url_option
from tools.fieldtool.statusclient import ServiceError, ServiceUnreachable, StatusClient

LAST_GOOD_SUFFIX = ".last-good"


@dataclass
class ApplyResult:
    written: bool
    backup: str | None  # path of the last good config kept, if any
    reload: str  # what the service said: "reloaded", "not running", "rejected: ...", "skipped"

    def lines(self, target: str) -> list[str]:
        out = [f"wrote {target}" if self.written else f"{target} left unchanged"]
        if self.backup:
            out.append(f"kept the previous good config as {self.backup}")
        out.append(f"service: {self.reload}")
        return out


def install_config(target: str | Path, data: dict, url: str | None = None, reload: bool = True) -> ApplyResult:
    """Validate ``data``, keep the current good config as TARGET.last-good, write TARGET
    atomically, and ask the running service at ``url`` to reload.

    Raises click.ClickException (target untouched) when ``data`` is invalid. When the service
    rejects the new file, the previous good file is put back.
    """
    target = Path(target)
    # relative paths in the config (store.path, file sources) are resolved against TARGET's dir
    try:
        parse_site(data, str(target))
    except ConfigError as e:
        raise click.ClickException(f"not applied, the config is invalid: {e}") from None
    text = tomli_w.dumps(data)
    backup = None
    if target.exists():
        try:
            parse_site(tomllib.loads(target.read_text(encoding="utf-8")), str(target))
            good = True
        except (ConfigError, tomllib.TOMLDecodeError, UnicodeDecodeError):
            good = False
        if good:
            backup = str(target) + LAST_GOOD_SUFFIX
            atomic_write(backup, target.read_bytes())
    atomic_write(target, text)
    if not reload:
        return ApplyResult(True, backup, "reload skipped (--no-reload)")
    client = StatusClient(service_url(url, str(target)))
    try:
        msg = client.reload()
        return ApplyResult(True, backup, f"reloaded ({client.url}){': ' + msg if msg else ''}")
    except ServiceUnreachable:
        return ApplyResult(True, backup, f"not running at {client.url}; the new config is used at the next start")
    except ServiceError as e:
        if e.status == 400 and backup:
            atomic_write(target, Path(backup).read_bytes())
            raise click.ClickException(
                f"the service rejected the new config ({e.message}); it keeps running the old one and "
                f"{target} was restored from {backup}"
            ) from None
        if e.status == 403:
            return ApplyResult(True, backup, f"reload refused (status.allow_commands is off); restart the service to use it")
        raise click.ClickException(f"written, but the reload failed: {e}") from None


def _flatten(d, prefix: str = "") -> dict[str, object]:
    out: dict[str, object] = {}
    if isinstance(d, dict):
        for k, v in d.items():
            out.update(_flatten(v, f"{prefix}.{k}" if prefix else k))
    elif isinstance(d, list) and d and all(isinstance(x, dict) for x in d):
        for i, v in enumerate(d):
            out.update(_flatten(v, f"{prefix}[{i}]"))
    else:
        out[prefix] = d
    return out


def diff_configs(a: dict, b: dict) -> list[str]:
    """Key-level differences: '- key = old', '+ key = new', '~ key: old -> new'."""
    fa, fb = _flatten(a), _flatten(b)
    lines = []
    for k in sorted(set(fa) | set(fb)):
        if k not in fb:
            lines.append(f"- {k} = {json.dumps(fa[k])}")
        elif k not in fa:
            lines.append(f"+ {k} = {json.dumps(fb[k])}")
        elif fa[k] != fb[k]:
            lines.append(f"~ {k}: {json.dumps(fa[k])} -> {json.dumps(fb[k])}")
    return lines


@click.group("config")
def config() -> None:
    """Validate, show, compare and safely apply site configs.

    \b
    Examples:
      roadwatch config validate new.toml
      roadwatch config show -c /etc/roadwatch/config.toml --section lanes
      roadwatch config diff new.toml                  # against the installed config
      roadwatch config apply new.toml                 # validate, install, reload service
    """


@config.command("validate")
@click.argument("files", nargs=-1, type=click.Path(dir_okay=False))
@config_option
def validate(files: tuple[str, ...], config_path: str) -> None:
    """Check config files (default: the installed one); exit 1 naming the key if one is bad.

    \b
    Example:
      roadwatch config validate site.toml
    """
    bad = 0
    for f in files or (config_path,):
        try:
            from appliance.config import load_site

            cfg = load_site(f)
        except ConfigError as e:
            click.echo(f"INVALID {e}", err=True)
            bad += 1
            continue
        click.echo(
            f"ok {f}: site {cfg.site.name!r}, {len(cfg.lanes)} lanes, {len(cfg.loops)} loops "
            f"(channels {sorted(cfg.loop_by_channel()) or '-'}), source {cfg.source.url}"
        )
    if bad:
        raise SystemExit(1)


@config.command("show")
@config_option
@click.option("--section", default=None, help="Only this top-level section (e.g. lanes, outputs).")
@click.option("--raw", is_flag=True, help="The file as written, without defaults.")
@click.option("--json", "as_json", is_flag=True, help="JSON instead of TOML.")
def show(config_path: str, section: str | None, raw: bool, as_json: bool) -> None:
    """Print the effective config: the file plus every default and derived geometry.

    \b
    Example:
      roadwatch config show --section loops
    """
    if raw:
        data = read_toml(config_path)
    else:
        data = to_dict(load_config(config_path))
    if section is not None:
        if section not in data:
            raise click.ClickException(f"no section {section!r}; sections: {', '.join(data)}")
        data = {section: data[section]}
    click.echo(json.dumps(data, indent=2) if as_json else tomli_w.dumps(data).rstrip())


@config.command("diff")
@click.argument("new", type=click.Path(dir_okay=False))
@click.argument("old", required=False, type=click.Path(dir_okay=False))
@config_option
@click.option("--text", is_flag=True, help="A unified text diff instead of a key-level one.")
def diff(new: str, old: str | None, config_path: str, text: bool) -> None:
    """Show what NEW changes compared with OLD (default: the installed config).

    \b
    Example:
      roadwatch config diff new.toml /etc/roadwatch/config.toml
    """
    old = old or config_path
    if text:
        a = Path(old).read_text(encoding="utf-8").splitlines() if Path(old).exists() else []
        b = Path(new).read_text(encoding="utf-8").splitlines()
        lines = list(difflib.unified_diff(a, b, old, new, lineterm=""))
    else:
        lines = diff_configs(read_toml(old) if Path(old).exists() else {}, read_toml(new))
    click.echo("\n".join(lines) if lines else "no differences")


@config.command("apply")
@click.argument("new", type=click.Path(exists=True, dir_okay=False))
@config_option
@url_option
@click.option("--reload/--no-reload", default=True, show_default=True, help="Ask the running service to reload.")
def apply(new: str, config_path: str, url: str | None, reload: bool) -> None:
    """Install NEW as the config: validate, keep the last good one, write atomically, reload.

    A config that does not validate, or that the running service rejects, never replaces
    the good one (the previous file is kept as CONFIG.last-good).

    \b
    Example:
      roadwatch config apply new.toml -c /etc/roadwatch/config.toml
    """
    data = read_toml(new)
    if Path(new).resolve() == Path(config_path).resolve():
        raise click.ClickException("NEW is the installed config itself; edit a copy and apply that")
    for line in diff_configs(read_toml(config_path), data) if Path(config_path).exists() else []:
        click.echo(line)
    result = install_config(config_path, data, url, reload)
    for line in result.lines(config_path):
        click.echo(line)
