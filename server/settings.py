"""Server settings: one pydantic-settings class, read from ``DRONESIM_*`` environment variables
and validated at start-up, so that a bad value stops the server with a clear message."""

from __future__ import annotations

from pathlib import Path
from typing import Literal
from urllib.parse import urlsplit

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    """Every setting of the server, with its default."""

    model_config = SettingsConfigDict(env_prefix="DRONESIM_", extra="ignore")

    host: str = "127.0.0.1"
    port: int = Field(8000, ge=1, le=65535)
    data_dir: Path = Path("data")  # sessions' maps and trajectories live here
    tls: bool = False  # serve HTTPS with a self-signed certificate kept in data_dir/tls
    max_sessions: int = Field(16, ge=1)  # live sessions at once; more get 503
    # Refused before decoding; at most uvicorn's ws_max_size (16 MiB), which refuses larger first.
    max_message_bytes: int = Field(4 * 1024 * 1024, ge=1024, le=16 * 1024 * 1024)
    session_ttl_s: float = Field(300.0, gt=0)  # a disconnected session is closed after this
    snapshot_interval_s: float = Field(10.0, gt=0)  # periodic atomic snapshot of map + trajectory
    fuse_every: int = Field(3, ge=1)  # integrate every n-th tracked frame (and every keyframe)
    voxel_m: float = Field(0.02, gt=0.001, le=0.2)  # TSDF voxel edge
    preview_points: int = Field(4000, ge=100)  # points per map preview chunk
    # Native threads (OpenCV, Open3D, BLAS) per session's worker process; 0 shares the machine's
    # cores among the live sessions, rebalanced as they come and go.
    worker_threads: int = Field(0, ge=0, le=256)
    demo: bool = False  # start a session that replays the bundled demo sequence
    demo_fps: float = Field(15.0, gt=0, le=60)
    cors_origins: list[str] = []  # extra allowed origins; same origin is always allowed
    create_rate_per_min: float = Field(30.0, ge=0)  # sessions one client IP may create; 0: no limit
    create_burst: int = Field(20, ge=1)  # ...of which this many at once
    # Reverse proxies whose X-Forwarded-For / -Proto are believed (uvicorn's forwarded_allow_ips:
    # comma-separated addresses or networks, "*" for any); the rate limit then counts the phone's
    # address, not the proxy's. Others' forwarding headers are ignored, so they cannot forge one.
    forwarded_allow_ips: str = "127.0.0.1"
    # "jemalloc": serve restarts itself on jemalloc when installed (see server/memory.py);
    # "system": keep the C library's malloc.
    allocator: Literal["jemalloc", "system"] = "jemalloc"
    # Run each session as a Ray actor on this cluster instead of a local worker process:
    # "auto" (the cluster this machine is part of), "ray://head:10001" (Ray Client), "host:6379",
    # or "local" (start a local instance). None: local processes, Ray not imported. Needs the
    # [ray] extra; see server/sessions/ray_workers.py and the README.
    ray: str | None = None

    @field_validator("data_dir")
    @classmethod
    def _data_dir_usable(cls, v: Path) -> Path:
        if v.exists() and not v.is_dir():
            raise ValueError(f"data_dir {v} exists and is not a folder")
        return v

    @field_validator("cors_origins")
    @classmethod
    def _exact_origins(cls, v: list[str]) -> list[str]:
        for origin in v:
            parts = urlsplit(origin)
            if (
                "*" in origin
                or parts.scheme not in ("http", "https")
                or not parts.netloc
                or (parts.path or parts.query or parts.fragment)
            ):
                raise ValueError(
                    f"cors origin {origin!r} must be exactly scheme://host[:port] "
                    "(no wildcard, no path): a wildcard lets any page call the API"
                )
        return v
