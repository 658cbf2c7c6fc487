"""sd_notify without libsystemd: READY=1, WATCHDOG=1, STATUS=... datagrams to $NOTIFY_SOCKET."""

from __future__ import annotations

import logging
import os
import socket

log = logging.getLogger(__name__)


class SystemdNotifier:
    """Sends notifications when run under systemd (Type=notify); does nothing otherwise."""

    def __init__(self, address: str | None = None):
        addr = address if address is not None else os.environ.get("NOTIFY_SOCKET", "")
        self.address = ("\0" + addr[1:]) if addr.startswith("@") else addr
        self.sock: socket.socket | None = None
        if self.address:
            self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
        usec = os.environ.get("WATCHDOG_USEC")
        self.watchdog_s = int(usec) / 1e6 if usec and usec.isdigit() else None
        self._failing = False  # a failed send is logged once, not at every watchdog ping

    @property
    def enabled(self) -> bool:
        return self.sock is not None

    def notify(self, message: str) -> bool:
        """Send one notification; False when not under systemd or the send failed (logged once per outage)."""
        if self.sock is None:
            return False
        try:
            self.sock.sendto(message.encode("utf-8", "replace"), self.address)
        except OSError as e:
            if not self._failing:
                log.warning("systemd notify to %r failed: %s", self.address, e)
            self._failing = True
            return False
        if self._failing:
            log.info("systemd notify to %r works again", self.address)
        self._failing = False
        return True

    def ready(self, status: str = "") -> bool:
        return self.notify("READY=1" + (f"\nSTATUS={status}" if status else ""))

    def watchdog(self) -> bool:
        return self.notify("WATCHDOG=1")

    def status(self, text: str) -> bool:
        return self.notify(f"STATUS={text}")

    def stopping(self) -> bool:
        return self.notify("STOPPING=1")

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
            self.sock = None
