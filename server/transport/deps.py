"""FastAPI dependencies: the session manager, the session a request's token opens, and the
per-client rate limit on creating sessions."""

from __future__ import annotations

import math
import threading
import time
from typing import Annotated

from fastapi import Depends, Header, Request

from server.config import Config, ServerConfig
from server.sessions import LiveSession, SessionError, SessionManager


class RateLimited(SessionError):
    """Too many requests from one client; ``retry_after_s`` says when the next one may pass."""

    def __init__(self, message: str, retry_after_s: float) -> None:
        super().__init__("rate_limited", message)
        self.retry_after_s = retry_after_s


class RateLimiter:
    """A token bucket per client key: ``burst`` requests at once, then ``per_min`` a minute.

    Buckets that have refilled are forgotten once ``max_keys`` clients are tracked, so memory
    stays bounded whatever addresses arrive."""

    def __init__(self, per_min: float, burst: int, max_keys: int = 10_000) -> None:
        self.rate_per_s, self.burst, self.max_keys = per_min / 60.0, burst, max_keys
        self._buckets: dict[str, tuple[float, float]] = {}  # key -> (tokens, at monotonic time)
        self._lock = threading.Lock()

    def _tokens(self, key: str, now: float) -> float:
        tokens, at = self._buckets.get(key, (self.burst, now))
        return min(self.burst, tokens + (now - at) * self.rate_per_s)

    def take(self, key: str) -> float:
        """Spend one request of ``key``: 0 when allowed, else the seconds until one is."""
        if self.rate_per_s <= 0:
            return 0.0
        now = time.monotonic()
        with self._lock:
            tokens = self._tokens(key, now)
            if tokens < 1:
                return (1 - tokens) / self.rate_per_s
            if key not in self._buckets and len(self._buckets) >= self.max_keys:
                recent = sorted(self._buckets.items(), key=lambda kv: kv[1][1])
                self._buckets = {
                    k: v
                    for k, v in recent[-self.max_keys // 2 :]
                    if self._tokens(k, now) < self.burst
                }
            self._buckets[key] = (tokens - 1, now)
            return 0.0


def get_manager(request: Request) -> SessionManager:
    return request.app.state.manager


def get_config(request: Request) -> Config:
    return request.app.state.config


def get_settings(request: Request) -> ServerConfig:
    """The configuration's server section."""
    return request.app.state.settings


def bearer_token(authorization: Annotated[str | None, Header()] = None) -> str | None:
    """The token of an ``Authorization: Bearer <token>`` header, or None."""
    if authorization is None:
        return None
    scheme, _, token = authorization.partition(" ")
    return token.strip() if scheme.lower() == "bearer" and token.strip() else None


def authorized_session(
    session_id: str,
    manager: Annotated[SessionManager, Depends(get_manager)],
    token: Annotated[str | None, Depends(bearer_token)],
) -> LiveSession | dict:
    """The live session, or a closed session's saved meta, that the token opens."""
    return manager.authorize(session_id, token)


def creation_allowed(request: Request) -> None:
    """Refuse a client (by IP) that creates sessions faster than the settings allow."""
    limiter: RateLimiter = request.app.state.create_limiter
    wait_s = limiter.take(request.client.host if request.client else "unknown")
    if wait_s > 0:
        raise RateLimited(
            f"too many new sessions from this address; try again in {math.ceil(wait_s)} s",
            retry_after_s=wait_s,
        )


ManagerDep = Annotated[SessionManager, Depends(get_manager)]
ConfigDep = Annotated[Config, Depends(get_config)]
SettingsDep = Annotated[ServerConfig, Depends(get_settings)]
SessionDep = Annotated[LiveSession | dict, Depends(authorized_session)]
