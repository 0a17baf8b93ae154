"""The one configuration: four sections, each the object its stage takes, with every default in
the section's own class.

- ``registration`` (server/registration/config.py): the tracker's parameters;
- ``mapping`` (server/mapping/config.py): a session's TSDF, fusion rate, map preview;
- ``simulation`` (server/simulation/config.py): the drone's physics, controller, behaviour;
- ``server`` (``ServerConfig`` below): the web server and its sessions.

The numerical sections are plain frozen dataclasses, so the core never imports pydantic; here
pydantic validates them (types, unknown keys) and their own checks run as they are built.

Where values come from, the later over the earlier (``load_config``):

1. the defaults;
2. a YAML or TOML file (``--config FILE``);
3. the environment: ``DRONESIM_`` + the key, sections nested with ``__``
   (``DRONESIM_REGISTRATION__SOLVER__DENSE=false``), and the documented flat server variables
   (``DRONESIM_PORT``, ``DRONESIM_VOXEL_M``, ... as listed in ``FLAT_ENV``), which the nested
   form overrides;
4. the command line: ``--set registration.keyframes.max_rotation_deg=10`` (repeatable), and the
   flags of ``serve``.

A bad value or an unknown key raises ``ConfigError`` naming the key, before anything starts.
"""

from __future__ import annotations

import ipaddress
import json
import os
import re
import sys
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any, Literal
from urllib.parse import urlsplit

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator
from pydantic_settings import (
    BaseSettings,
    EnvSettingsSource,
    PydanticBaseSettingsSource,
    SettingsConfigDict,
)

from server.errors import ConfigError
from server.mapping.config import MappingConfig
from server.registration.config import RegistrationConfig
from server.simulation.config import SimulationConfig

ENV_PREFIX = "DRONESIM_"


class ServerConfig(BaseModel):
    """The web server and its sessions."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    host: str = "127.0.0.1"
    port: int = Field(default=8000, ge=1, le=65535)
    data_dir: Path = Path("data")  # sessions' maps and trajectories live here
    tls: bool = False  # serve HTTPS with a self-signed certificate kept in data_dir/tls
    # Addresses or names phones reach this server by, beyond the LAN addresses it finds itself
    # (server/transport/phone_link.py): a container's host's LAN address, which the container
    # cannot see. Named in the TLS certificate, and first in the phone URL that serve prints.
    # The flat variable DRONESIM_PHONE_HOSTS takes them comma-separated.
    phone_hosts: list[str] = []
    max_sessions: int = Field(default=16, ge=1)  # live sessions at once; more get 503
    # Refused before decoding; at most uvicorn's ws_max_size (16 MiB), which refuses larger first.
    max_message_bytes: int = Field(default=4 * 1024 * 1024, ge=1024, le=16 * 1024 * 1024)
    # Largest iPhone recording the page may upload (POST /api/recordings), megabytes.
    max_upload_mb: float = Field(default=1000.0, gt=0)
    # An upload is converted in a process of its own (server/transport/recordings.py): the
    # memory it may take beyond what the process starts with (address space, megabytes), and
    # how long it may run, seconds. A file that inflates past either is refused (422); the web
    # process and its sessions never see the cost.
    upload_memory_mb: float = Field(default=2000.0, ge=64)
    upload_convert_s: float = Field(default=600.0, gt=0)
    # What an upload may declare, checked before anything is decoded (server/datasets/bounds.py):
    # pixels in any one image or video frame (megapixels), frames, and metadata text (megabytes).
    upload_max_megapixels: float = Field(default=16.8, gt=0, le=268)
    upload_max_frames: int = Field(default=100_000, ge=1)
    upload_max_metadata_mb: float = Field(default=64.0, gt=0)
    session_ttl_s: float = Field(default=300.0, gt=0)  # a disconnected session closes after this
    snapshot_interval_s: float = Field(default=10.0, gt=0)  # atomic snapshot of map + trajectory
    # Every session keeps its keyframes (ORB features, JPEG + PNG, ~270 KB each, written by its
    # mapping thread) and leaves a room when it closes; false: no rooms, no such work.
    save_rooms: bool = True
    drone_state_hz: float = Field(default=20.0, gt=0, le=60)  # drone_state messages per second
    # Flight recordings (server/sessions/flight_store.py): the longest stretch of one flight kept,
    # seconds (beyond it the flight is marked truncated), and the newest flights a session keeps.
    flight_max_s: float = Field(default=600.0, gt=0, le=3600)
    flights_kept: int = Field(default=20, ge=1, le=1000)
    # Viewer links (read-only watchers of a live session) at once per session.
    max_viewers: int = Field(default=8, ge=0, le=64)
    # Phones in one shared room (the owner's session and those that joined it with an invite).
    max_room_phones: int = Field(default=3, ge=1, le=16)
    # Native threads (OpenCV, Open3D, BLAS) per session's worker process; 0 shares the machine's
    # cores less one among the live sessions, rebalanced as they come and go.
    worker_threads: int = Field(default=0, ge=0, le=256)
    demo: bool = False  # start a session that replays the bundled demo sequence
    demo_fps: float = Field(default=15.0, gt=0, le=60)
    cors_origins: list[str] = []  # extra allowed origins; same origin is always allowed
    # Sessions one client IP may create per minute (0: no limit), this many of them at once.
    create_rate_per_min: float = Field(default=30.0, ge=0)
    create_burst: int = Field(default=20, ge=1)
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
    # [ray] extra; see server/sessions/processes/ray_workers.py and docs/SCALING.md.
    ray: str | None = None

    @field_validator("data_dir")
    @classmethod
    def _data_dir_usable(cls, v: Path) -> Path:
        if v.exists() and not v.is_dir():
            raise ValueError(f"data_dir {v} exists and is not a folder")
        return v

    @field_validator("phone_hosts", mode="before")
    @classmethod
    def _comma_separated(cls, v: Any) -> Any:
        return [h.strip() for h in v.split(",") if h.strip()] if isinstance(v, str) else v

    @field_validator("phone_hosts")
    @classmethod
    def _host_names(cls, v: list[str]) -> list[str]:
        for host in v:
            # A bare host: the certificate names it and the phone URL adds scheme and port.
            try:
                ipaddress.ip_address(host)
                continue
            except ValueError:
                pass
            if not re.fullmatch(r"[A-Za-z0-9-]+(\.[A-Za-z0-9-]+)*", host):
                raise ValueError(
                    f"phone host {host!r} must be an address or a host name "
                    "(no scheme, port or path), e.g. 192.168.1.20"
                )
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


# The flat variables the README documented before the sections existed: DRONESIM_<NAME> sets
# the key at this path. Every server key keeps its flat name; three map keys were server
# settings too.
FLAT_ENV: dict[str, tuple[str, ...]] = {
    **{name: ("server", name) for name in ServerConfig.model_fields},
    "voxel_m": ("mapping", "tsdf", "voxel_m"),
    "fuse_every": ("mapping", "fuse_every"),
    "preview_points": ("mapping", "preview_points"),
}
_JSON_VALUED = {"cors_origins"}  # flat variables that hold a JSON list


class Config(BaseSettings):
    """The whole configuration. ``Config()`` reads the environment over the defaults;
    ``load_config`` adds a file and command-line overrides; ``Config.defaults()`` reads nothing."""

    model_config = SettingsConfigDict(
        env_prefix=ENV_PREFIX, env_nested_delimiter="__", extra="forbid", frozen=True
    )

    registration: RegistrationConfig = Field(default_factory=RegistrationConfig)
    mapping: MappingConfig = Field(default_factory=MappingConfig)
    simulation: SimulationConfig = Field(default_factory=SimulationConfig)
    server: ServerConfig = Field(default_factory=ServerConfig)

    @field_validator("registration", "mapping", "simulation", mode="wrap")
    @classmethod
    def _section_checks(cls, value: Any, handler: Any) -> Any:
        # The sections' own consistency checks raise ConfigError (the core knows no pydantic);
        # as a ValueError it is reported with the section's name like any other bad value.
        try:
            return handler(value)
        except ConfigError as exc:
            raise ValueError(str(exc)) from exc

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        # Keyword arguments, then nested variables, then flat ones; no .env or secrets files.
        return init_settings, env_settings, FlatEnvSource(settings_cls)

    @classmethod
    def defaults(cls) -> Config:
        """Every default, whatever the environment holds. (Validation would read the
        environment: pydantic calls BaseSettings' __init__; the defaults are valid as built.)"""
        return cls.model_construct()

    def to_dict(self) -> dict:
        """Plain values (lists, strings, numbers), as written to a file and read back."""
        return self.model_dump(mode="json")

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.to_dict(), sort_keys=False)


class FlatEnvSource(PydanticBaseSettingsSource):
    """The documented flat ``DRONESIM_<NAME>`` variables, each put where its key lives."""

    def get_field_value(self, field, field_name):  # the whole lookup happens in __call__
        return None, field_name, False

    def __call__(self) -> dict[str, Any]:
        upper = {k.upper(): v for k, v in os.environ.items() if k.upper().startswith(ENV_PREFIX)}
        values: dict[str, Any] = {}
        for name, path in FLAT_ENV.items():
            key = ENV_PREFIX + name.upper()
            if key not in upper:
                continue
            raw = upper[key]
            if name in _JSON_VALUED:
                try:
                    raw = json.loads(raw)
                except json.JSONDecodeError as exc:
                    raise ConfigError(f"{key} must be a JSON list: {exc}") from exc
            _set_path(values, path, raw, key)
        return values


# ---- loading ------------------------------------------------------------------------------------


def load_config(
    path: Path | str | None = None,
    overrides: Iterable[str] = (),
    flags: Mapping[str, Any] | None = None,
) -> Config:
    """The effective configuration: defaults < ``path`` (YAML or TOML) < environment (flat
    variables < nested ones) < ``overrides`` (``"section.key=value"``, the value in YAML
    syntax) < ``flags`` (nested values, from a command's own options). Raises ConfigError
    naming every bad or unknown key."""
    values = read_config_file(Path(path)) if path is not None else {}
    values = _merge(values, FlatEnvSource(Config)())
    values = _merge(values, EnvSettingsSource(Config)())
    values = _merge(values, parse_overrides(overrides))
    values = _merge(values, flags or {})
    return validate_config(values)


def validate_config(values: Mapping[str, Any]) -> Config:
    """``values`` (nested sections, as in a file) over the defaults, validated."""
    try:
        return Config.model_validate(values)
    except ValidationError as exc:
        raise ConfigError(describe_errors(exc)) from exc


def describe_errors(exc: ValidationError) -> str:
    """One line per problem, each naming its key as ``section.key``."""
    lines = []
    for error in exc.errors():
        key = ".".join(str(part) for part in error["loc"]) or "(top level)"
        message = error["msg"].removeprefix("Value error, ")
        if error["type"] in ("unexpected_keyword_argument", "extra_forbidden"):
            lines.append(f"{key}: unknown key")
        elif isinstance(error["input"], (dict, list)):  # a section's own check names its keys
            lines.append(message if message.startswith(key) else f"{key}: {message}")
        else:
            lines.append(f"{key}: {message} (got {error['input']!r})")
    return "invalid configuration:\n  " + "\n  ".join(lines)


def read_config_file(path: Path) -> dict[str, Any]:
    """A configuration file: YAML (.yaml, .yml) or TOML (.toml), sections at the top level."""
    try:
        text = path.read_text()
    except OSError as exc:
        raise ConfigError(f"cannot read configuration file {path}: {exc.strerror}") from exc
    suffix = path.suffix.lower()
    try:
        if suffix in (".yaml", ".yml"):
            values = yaml.safe_load(text)
        elif suffix == ".toml":
            if sys.version_info >= (3, 11):
                import tomllib
            else:
                import tomli as tomllib

            values = tomllib.loads(text)
        else:
            raise ConfigError(f"configuration file {path}: expected .yaml, .yml or .toml")
    except (yaml.YAMLError, ValueError) as exc:
        raise ConfigError(f"configuration file {path} is not valid {suffix[1:]}: {exc}") from exc
    if values is None:  # an empty file: the defaults
        return {}
    if not isinstance(values, dict):
        raise ConfigError(f"configuration file {path} must hold a mapping of sections")
    return values


def parse_overrides(overrides: Iterable[str]) -> dict[str, Any]:
    """``["registration.solver.dense=false", ...]`` as nested values; each value is read as
    YAML (``10``, ``false``, ``[1, 2, 3]``, or a string)."""
    values: dict[str, Any] = {}
    for item in overrides:
        key, sep, raw = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE, e.g. server.port=8080")
        try:
            value = yaml.safe_load(raw) if raw.strip() else ""
        except yaml.YAMLError as exc:
            raise ConfigError(f"--set {key}: cannot read the value {raw!r}: {exc}") from exc
        _set_path(values, tuple(key.split(".")), value, f"--set {key}")
    return values


def write_config(config: Config, path: Path) -> Path:
    """Write ``config`` as YAML, to be read back with ``--config``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(config.to_yaml())
    return path


def _set_path(values: dict[str, Any], path: tuple[str, ...], value: Any, origin: str) -> None:
    node = values
    for part in path[:-1]:
        node = node.setdefault(part, {})
        if not isinstance(node, dict):
            raise ConfigError(f"{origin}: {'.'.join(path)} is below a key that holds a value")
    node[path[-1]] = value


def _merge(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """``over`` on top of ``base``, section by section, key by key."""
    merged = dict(base)
    for key, value in over.items():
        if isinstance(value, Mapping) and isinstance(merged.get(key), Mapping):
            merged[key] = _merge(merged[key], value)
        else:
            merged[key] = value
    return merged
