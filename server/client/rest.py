"""The REST calls a protocol client makes: create a session, read its status, delete it.

Blocking (urllib, so that a client needs no HTTP library); async callers run them in a thread.
"""

from __future__ import annotations

import json
import logging
import ssl as ssl_module
import urllib.error
import urllib.request

log = logging.getLogger(__name__)

HTTP_TIMEOUT_S = 30.0


def ssl_context(url: str, insecure: bool = False) -> ssl_module.SSLContext | None:
    """None for http/ws; for https/wss the default context, or one that accepts any certificate
    (the server's self-signed one) when ``insecure``."""
    if not url.startswith(("https", "wss")):
        return None
    context = ssl_module.create_default_context()
    if insecure:
        context.check_hostname, context.verify_mode = False, ssl_module.CERT_NONE
    return context


def request(
    method: str, url: str, token: str | None = None, context: ssl_module.SSLContext | None = None
) -> tuple[int, dict | None]:
    """One HTTP request -> (status, JSON body or None); status 0 when the server cannot be
    reached. ``token`` goes in the Authorization header, never in the URL."""
    req = urllib.request.Request(url, method=method)
    if token is not None:
        req.add_header("Authorization", f"Bearer {token}")
    try:
        with urllib.request.urlopen(req, timeout=HTTP_TIMEOUT_S, context=context) as response:
            body = response.read()
            return response.status, json.loads(body) if body else None
    except urllib.error.HTTPError as exc:
        return exc.code, None
    except (urllib.error.URLError, OSError) as exc:
        log.warning("%s %s: %s", method, url, exc)
        return 0, None


def sessions_url(base_url: str, session_id: str | None = None) -> str:
    """http(s)://host:port/api/sessions[/id] from the server's base URL."""
    url = f"{base_url.rstrip('/')}/api/sessions"
    return url if session_id is None else f"{url}/{session_id}"


def websocket_url(base_url: str, session_id: str) -> str:
    """ws(s)://host:port/ws/sessions/{id} from the server's http(s) or ws(s) base URL."""
    base = base_url.rstrip("/")
    if base.startswith("http"):
        base = "ws" + base[len("http") :]
    return f"{base}/ws/sessions/{session_id}"
