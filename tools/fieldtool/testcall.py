"""`roadwatch test-call`: force a detector call on a channel for cabinet wiring tests."""

from __future__ import annotations

import time

import click

from tools.fieldtool.common import config_option, service_url, url_option
from tools.fieldtool.statusclient import ServiceError, ServiceUnreachable, StatusClient


def channel_state(st: dict, channel: int) -> dict | None:
    return next((c for c in st.get("channels", []) if c.get("channel") == channel), None)


@click.command("test-call")
@click.argument("channel", type=click.IntRange(min=1))
@click.option("--seconds", "-s", type=click.FloatRange(min=0), default=10.0, show_default=True,
              help="How long the call is held; the service ends it by itself (0 = end a forced call now).")
@click.option("--watch", is_flag=True, help="Follow the channel's call state until the call ends.")
@config_option
@url_option
def test_call(channel: int, seconds: float, watch: bool, config_path: str, url: str | None) -> None:
    """Force a detector call on CHANNEL for N seconds (cabinet wiring test).

    The service ends the call by itself after --seconds (capped by outputs.force_call_max_s),
    even if this command is interrupted.

    \b
    Examples:
      roadwatch test-call 3 --seconds 10
      roadwatch test-call 3 --seconds 5 --watch
    """
    client = StatusClient(service_url(url, config_path))
    try:
        before = channel_state(client.status(), channel)
    except (ServiceError, ServiceUnreachable) as e:
        raise click.ClickException(str(e)) from None
    if before is None:
        raise click.ClickException(f"channel {channel} is not configured on this detector")
    try:
        client.force_call(channel, seconds)
    except ServiceError as e:
        if e.status == 403:
            raise click.ClickException(f"the service refuses commands: {e.message}") from None
        raise click.ClickException(f"force call on channel {channel} refused: {e.message}") from None
    except ServiceUnreachable as e:
        raise click.ClickException(str(e)) from None
    t0 = time.monotonic()
    what = f"forced ON for {seconds:g} s" if seconds > 0 else "force released"
    click.echo(f"channel {channel} (loop {before.get('loop_id')}, lane {before.get('lane')}): {what}; "
               "the service switches it off by itself")
    time.sleep(0.3)
    try:
        now = channel_state(client.status(), channel) or {}
    except (ServiceError, ServiceUnreachable) as e:
        raise click.ClickException(f"call requested, but the status is unreadable now: {e}") from None
    click.echo(f"now: call={'ON' if now.get('call') else 'off'} forced={bool(now.get('forced'))}")
    if seconds > 0 and not now.get("forced"):
        raise click.ClickException(f"the service accepted the request but channel {channel} does not show forced")
    if not watch or seconds <= 0:
        return
    last = None
    with click.progressbar(length=int(seconds * 10), label=f"channel {channel} forced") as bar:
        while True:
            try:
                now = channel_state(client.status(), channel) or {}
            except (ServiceError, ServiceUnreachable) as e:
                raise click.ClickException(str(e)) from None
            elapsed = time.monotonic() - t0
            bar.update(min(int(elapsed * 10), int(seconds * 10)) - bar.pos)
            if not now.get("forced"):
                last = elapsed
                break
            if elapsed > seconds + 5.0:
                raise click.ClickException(f"channel {channel} is still forced {elapsed:.0f} s after a {seconds:g} s call")
            time.sleep(0.2)
    click.echo(f"channel {channel} released after {last:.1f} s")
