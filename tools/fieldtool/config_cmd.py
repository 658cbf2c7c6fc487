"""`roadwatch config validate | show | diff | apply`: check and safely install site configs."""

from __future__ import annotations

import difflib
import json
import tomllib
from dataclasses import dataclass
from pathlib import Path

import click
import tomli_w

from appliance.config import ConfigError, SiteConfig, load_site, parse_site, to_dict
from tools.fieldtool.common import config_option, load_config, read_toml, service_url, url_option, write_file
from tools.fieldtool.statusclient import ServiceError, ServiceTimeout, ServiceUnreachable, StatusClient

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


def preflight(cfg: SiteConfig) -> list[str]:
    """Problems the schema cannot see: a file source that does not exist, a missing store directory."""
    base = Path(cfg.path).parent if cfg.path else Path.cwd()
    url = cfg.source.url
    out = []
    kind = url.split(":", 1)[0] if ":" in url and not url.startswith("/") else "file"
    if kind == "images":
        d = (base / url[len("images:"):]).parent
        if not d.is_dir():
            out.append(f"source.url: image directory {str(d)!r} does not exist")
    elif kind == "file" and not url.startswith("/dev/"):
        f = base / url
        if not f.is_file():
            out.append(f"source.url: video file {str(f)!r} does not exist")
    store_dir = (base / cfg.store.path).parent
    if not store_dir.is_dir():
        out.append(f"store.path: directory {str(store_dir)!r} does not exist")
    return out


def _is_good(path: Path) -> bool:
    try:
        parse_site(tomllib.loads(path.read_text(encoding="utf-8")), str(path))
        return True
    except (ConfigError, tomllib.TOMLDecodeError, UnicodeDecodeError, OSError):
        return False


def install_config(target: str | Path, data: dict, url: str | None = None, reload: bool = True,
                   text: str | None = None, draft_ok: bool = False) -> ApplyResult:
    """Validate ``data``, keep the current good config as TARGET.last-good, write TARGET
    atomically (``text`` verbatim if given, so comments survive; else ``data`` as TOML), and
    ask the running service at ``url`` to reload.

    Raises click.ClickException (target untouched) when ``data`` is invalid. When the service
    rejects the new file, the previous good file is put back. With ``draft_ok``, a site being
    set up (TARGET not a valid config yet) may be written while it still has no lanes.
    """
    target = Path(target)
    good = target.exists() and _is_good(target)
    # relative paths in the config (store.path, file sources) are resolved against TARGET's dir
    try:
        parse_site(data, str(target))
        draft = None
    except ConfigError as e:
        if not (draft_ok and not good and e.key == "lanes" and not data.get("lanes")):
            raise click.ClickException(f"not applied, the config is invalid: {e}") from None
        draft = e.problem
    text = tomli_w.dumps(data) if text is None else text
    running_url = service_url(url, str(target))  # where the service runs now (the old [status])
    backup = None
    if good:
        backup = str(target) + LAST_GOOD_SUFFIX
        write_file(backup, target.read_bytes())
    write_file(target, text)
    if draft is not None:
        return ApplyResult(True, backup, f"not reloaded: the site is not complete yet (lanes: {draft}); "
                                         "add lanes with `roadwatch zones lane`")
    if not reload:
        return ApplyResult(True, backup, "reload skipped (--no-reload)")
    client = StatusClient(running_url)
    try:
        msg = client.reload()
        return ApplyResult(True, backup, f"reloaded ({client.url}){': ' + msg if msg else ''}")
    except ServiceTimeout as e:
        return ApplyResult(True, backup, f"reload requested, but {e}; check with `roadwatch status`")
    except ServiceUnreachable:
        return ApplyResult(True, backup, f"not running at {client.url}; the new config is used at the next start")
    except ServiceError as e:
        if e.status == 400 and backup:
            write_file(target, Path(backup).read_bytes())
            raise click.ClickException(
                f"the service rejected the new config ({e.message}); it keeps running the old one and "
                f"{target} was restored from {backup}"
            ) from None
        if e.status == 403:
            return ApplyResult(True, backup, "reload refused (status.allow_commands is off); restart the service to use it")
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
            cfg = load_site(f)
        except ConfigError as e:
            click.echo(f"INVALID {e}", err=True)
            bad += 1
            continue
        for problem in preflight(cfg):
            click.echo(f"WARNING {f}: {problem}", err=True)
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
@click.option("--force", is_flag=True, help="Apply even if the source file or store directory is missing.")
def apply(new: str, config_path: str, url: str | None, reload: bool, force: bool) -> None:
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
    try:
        # paths in the file are relative to where it will be installed
        problems = preflight(parse_site(data, str(config_path)))
    except ConfigError as e:
        raise click.ClickException(f"not applied, the config is invalid: {e}") from None
    if problems and not force:
        raise click.ClickException("not applied: " + "; ".join(problems) + " (--force to apply anyway)")
    for line in diff_configs(read_toml(config_path), data) if Path(config_path).exists() else []:
        click.echo(line)
    result = install_config(config_path, data, url, reload, text=Path(new).read_text(encoding="utf-8"))
    for line in result.lines(config_path):
        click.echo(line)
