"""The local status endpoint: loopback HTTP (ThreadingHTTPServer) serving JSON status, the
latest frame as PNG, and force-call/reload commands for the config tool."""

from __future__ import annotations

import json
import logging
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any, Protocol
from urllib.parse import parse_qs, urlparse

log = logging.getLogger("roadwatch.status")

MAX_BODY = 64 * 1024


class StatusProvider(Protocol):
    allow_commands: bool

    def status(self) -> dict: ...

    def snapshot_png(self, overlay: bool) -> bytes | None: ...

    def force_call(self, channel: int, seconds: float) -> None: ...  # ValueError: bad channel

    def reload(self) -> None: ...  # ValueError (ConfigError): the message goes to the client


class _Handler(BaseHTTPRequestHandler):
    server_version = "roadwatch-status"
    provider: StatusProvider

    def log_message(self, fmt: str, *args: Any) -> None:
        log.debug("%s " + fmt, self.address_string(), *args)

    def _send(self, code: int, body: bytes, ctype: str = "application/json") -> None:
        self.send_response(code)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.write(body)

    def _json(self, code: int, obj: Any) -> None:
        self._send(code, json.dumps(obj, default=_jsonable).encode())

    def do_GET(self) -> None:
        url = urlparse(self.path)
        try:
            if url.path == "/api/status":
                self._json(200, self.provider.status())
            elif url.path == "/api/snapshot.png":
                overlay = parse_qs(url.query).get("overlay", ["1"])[-1] not in ("0", "false")
                png = self.provider.snapshot_png(overlay)
                if png is None:
                    self._json(503, {"ok": False, "error": "no frame yet"})
                else:
                    self._send(200, png, "image/png")
            else:
                self._json(404, {"ok": False, "error": f"no route {url.path}"})
        except Exception as e:  # noqa: BLE001 - the endpoint must answer, not die
            log.exception("status request failed")
            self._json(500, {"ok": False, "error": str(e)})

    def do_POST(self) -> None:
        url = urlparse(self.path)
        length = int(self.headers.get("Content-Length") or 0)
        if length > MAX_BODY:
            self._json(413, {"ok": False, "error": "body too large"})
            return
        raw = self.rfile.read(length) if length else b""
        if url.path not in ("/api/force-call", "/api/reload"):
            self._json(404, {"ok": False, "error": f"no route {url.path}"})
            return
        if not self.provider.allow_commands:
            self._json(403, {"ok": False, "error": "commands are disabled (status.allow_commands = false)"})
            return
        try:
            body = json.loads(raw or b"{}")
            if not isinstance(body, dict):
                raise ValueError("body must be a JSON object")
        except ValueError as e:
            self._json(400, {"ok": False, "error": f"bad JSON body: {e}"})
            return
        try:
            if url.path == "/api/force-call":
                ch, secs = body.get("channel"), body.get("seconds", 10.0)
                if not isinstance(ch, int) or isinstance(ch, bool):
                    raise ValueError(f"channel must be an integer, got {ch!r}")
                if not isinstance(secs, (int, float)) or isinstance(secs, bool) or secs < 0:
                    raise ValueError(f"seconds must be a non-negative number, got {secs!r}")
                self.provider.force_call(ch, float(secs))
            else:
                self.provider.reload()
        except ValueError as e:
            self._json(400, {"ok": False, "error": str(e)})
            return
        self._json(200, {"ok": True})


def _jsonable(o: Any) -> Any:
    if hasattr(o, "to_dict"):
        return o.to_dict()
    if hasattr(o, "item"):
        return o.item()
    return str(o)


class StatusServer:
    """Serves ``provider`` on host:port (port 0 picks a free one; see ``.port``)."""

    def __init__(self, host: str, port: int, provider: StatusProvider):
        handler = type("Handler", (_Handler,), {"provider": provider})
        self.httpd = ThreadingHTTPServer((host, port), handler)
        self.httpd.daemon_threads = True
        self.host, self.port = host, self.httpd.server_address[1]
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        self._thread = threading.Thread(target=self.httpd.serve_forever, name="status-http", daemon=True)
        self._thread.start()
        log.info("status endpoint on http://%s:%d/api/status", self.host, self.port)

    def stop(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()
        if self._thread:
            self._thread.join(timeout=5)
