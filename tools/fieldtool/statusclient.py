"""A tiny urllib client of the running service's loopback status API."""

from __future__ import annotations

import json
import urllib.error
import urllib.request


class ServiceError(Exception):
    """The service answered with an error status (``status`` holds the HTTP code)."""

    def __init__(self, status: int, message: str):
        self.status, self.message = status, message
        super().__init__(f"HTTP {status}: {message}")


class ServiceUnreachable(Exception):
    """Nothing answers at the status URL."""


class ServiceTimeout(ServiceUnreachable):
    """The service accepted the connection (or was slow to) but did not answer in time."""


class StatusClient:
    """GET /api/status, /api/snapshot.png; POST /api/force-call, /api/reload."""

    def __init__(self, url: str = "http://127.0.0.1:8765", timeout: float = 5.0):
        self.url = url.rstrip("/")
        self.timeout = timeout

    def _request(self, method: str, path: str, body: dict | None = None,
                 timeout: float | None = None) -> tuple[int, bytes]:
        data = json.dumps(body).encode() if body is not None else None
        req = urllib.request.Request(self.url + path, data=data, method=method)
        if data is not None:
            req.add_header("Content-Type", "application/json")
        timeout = self.timeout if timeout is None else timeout
        try:
            with urllib.request.urlopen(req, timeout=timeout) as resp:
                return resp.status, resp.read()
        except urllib.error.HTTPError as e:
            raw = e.read()
            raise ServiceError(e.code, _message(raw) or e.reason) from None
        except TimeoutError:
            raise ServiceTimeout(f"{self.url}{path} did not answer within {timeout:g} s") from None
        except (urllib.error.URLError, ConnectionError, OSError) as e:
            if isinstance(getattr(e, "reason", None), TimeoutError):
                raise ServiceTimeout(f"{self.url}{path} did not answer within {timeout:g} s") from None
            reason = getattr(e, "reason", e)
            raise ServiceUnreachable(f"no service answers at {self.url} ({reason})") from None

    def status(self) -> dict:
        _, raw = self._request("GET", "/api/status")
        try:
            return json.loads(raw)
        except ValueError:
            raise ServiceError(200, "status answer is not JSON") from None

    def snapshot_png(self, overlay: bool = False) -> bytes:
        _, raw = self._request("GET", f"/api/snapshot.png?overlay={int(overlay)}")
        if not raw.startswith(b"\x89PNG"):
            raise ServiceError(200, "snapshot answer is not a PNG")
        return raw

    def force_call(self, channel: int, seconds: float) -> str:
        _, raw = self._request("POST", "/api/force-call", {"channel": channel, "seconds": seconds})
        return _message(raw)

    def reload(self, timeout: float = 90.0) -> str:
        """Ask the service to re-read its config; it may rebuild (and compile) the pipeline first."""
        _, raw = self._request("POST", "/api/reload", {}, timeout=timeout)
        return _message(raw)


def _message(raw: bytes) -> str:
    """A human message from a JSON ({"error"|"message"|"detail": ...}) or plain-text body."""
    text = raw.decode("utf-8", "replace").strip()
    try:
        obj = json.loads(text)
    except ValueError:
        return text
    if isinstance(obj, dict):
        for k in ("error", "message", "detail", "status"):
            if isinstance(obj.get(k), str):
                return obj[k]
        return ""
    return text
