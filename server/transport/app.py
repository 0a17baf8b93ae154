"""The FastAPI application: wires the configuration, the session manager, the REST API and the
WebSocket."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import re
from collections.abc import Mapping

import uvicorn
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.middleware.cors import CORSMiddleware
from fastapi.openapi.utils import get_openapi
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from server import __version__
from server.config import Config
from server.datasets.bounds import DecodeLimits
from server.mapping.tsdf import MapError
from server.memory import this_process_allocator
from server.sessions import SessionError, SessionManager
from server.sessions.config import SessionConfig
from server.sessions.processes.session_process import warm_up
from server.sessions.store import SessionStore, StoreError
from server.transport import (
    routes_client,
    routes_flights,
    routes_phone,
    routes_races,
    routes_recordings,
    routes_sessions,
    routes_viewers,
    viewer_socket,
    websocket,
)
from server.transport.connections import end_all_connections
from server.transport.deps import RateLimiter
from server.transport.recordings import RecordingError, RecordingStore

log = logging.getLogger(__name__)

_STATUS = {
    "unauthorized": 401,
    "not_found": 404,
    "session_closed": 409,
    "too_many_viewers": 409,
    "room_unavailable": 409,
    "room_full": 409,
    "race_unavailable": 409,
    "rate_limited": 429,
    "server_full": 503,
}


def _error(
    code: str, message: str, status: int, headers: Mapping[str, str] | None = None
) -> JSONResponse:
    """The documented error answer (schemas.ErrorBody): ``{"error": {code, message}}``."""
    return JSONResponse(
        {"error": {"code": code, "message": message}}, status_code=status, headers=headers
    )


class RedactTokens(logging.Filter):
    """Blank out ``token=...`` in log lines: uvicorn logs each WebSocket's path with its query."""

    _TOKEN = re.compile(r"(token=)[^&\s\"']+")

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        if "token=" in message:
            record.msg, record.args = self._TOKEN.sub(r"\1[redacted]", message), ()
        return True


def create_app(config: Config | None = None) -> FastAPI:
    """The app for ``config`` (the environment over the defaults when None)."""
    config = config or Config()
    settings = config.server
    workers = None
    if settings.ray:  # sessions as Ray actors on a cluster (the optional extra [ray])
        from server.sessions.processes.ray_workers import RayWorkers

        workers = RayWorkers(settings.ray)
    manager = SessionManager(
        SessionStore(settings.data_dir),
        SessionConfig.from_config(config),
        settings.max_sessions,
        workers=workers,
        threads=settings.worker_threads,
        max_room_phones=settings.max_room_phones,
    )

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI):
        restored = manager.load_saved()
        app.state.recordings.clean()  # an upload cut off by the last stop
        log.info("data dir %s: %d saved sessions", settings.data_dir.resolve(), restored)
        # The workers' forkserver imports the numerical stack once (seconds): before the server
        # says it is up, so that creating a session never waits for it.
        if not settings.ray:
            await asyncio.to_thread(warm_up)
        reaper = asyncio.create_task(_reap(app))
        demo = None
        if settings.demo:
            from server.transport.demo import run_demo

            demo = asyncio.create_task(run_demo(app))
        try:
            yield
        finally:
            for task in (reaper, demo):
                if task is not None:
                    task.cancel()
            if settings.ray:  # the sessions live on in the cluster: let go of them, unstopped
                manager.workers.detach()
            unsaved = await asyncio.to_thread(manager.shutdown)
            await asyncio.to_thread(manager.workers.close)
            if unsaved:
                log.critical(
                    "could not save sessions %s at shutdown (see the errors above): "
                    "their maps since the last snapshot are lost",
                    ", ".join(unsaved),
                )

    app = FastAPI(title="AR drone simulator server", version=__version__, lifespan=lifespan)
    app.state.config = config
    app.state.settings = settings  # the server section, read by the routes and the socket
    app.state.manager = manager
    app.state.connections = {}  # session id -> its open WebSocket (connections.Connection)
    app.state.demo = None
    app.state.create_limiter = RateLimiter(settings.create_rate_per_min, settings.create_burst)
    app.state.recordings = RecordingStore(
        settings.data_dir / "recordings",
        int(settings.max_upload_mb * 1e6),
        memory_bytes=int(settings.upload_memory_mb * 2**20),
        convert_s=settings.upload_convert_s,
        limits=DecodeLimits(
            max_pixels=int(settings.upload_max_megapixels * 1e6),
            max_frames=settings.upload_max_frames,
            max_metadata_bytes=int(settings.upload_max_metadata_mb * 1e6),
        ),
    )
    for name in ("uvicorn.error", "uvicorn.access"):
        logger = logging.getLogger(name)
        if not any(isinstance(f, RedactTokens) for f in logger.filters):
            logger.addFilter(RedactTokens())
    if settings.cors_origins:
        app.add_middleware(
            CORSMiddleware,
            allow_origins=settings.cors_origins,
            allow_methods=["GET", "POST", "DELETE"],
            allow_headers=["Authorization"],
        )
    app.include_router(routes_sessions.router)
    app.include_router(routes_flights.router)
    app.include_router(routes_races.router)
    app.include_router(routes_viewers.router)
    app.include_router(websocket.router)
    app.include_router(viewer_socket.router)
    app.include_router(routes_client.router)
    app.include_router(routes_recordings.router)
    app.include_router(routes_phone.router)

    @app.exception_handler(SessionError)
    async def session_error(request: Request, exc: SessionError) -> JSONResponse:
        retry = getattr(exc, "retry_after_s", None)
        headers = {"Retry-After": str(math.ceil(retry))} if retry else None
        return _error(exc.code, str(exc), _STATUS.get(exc.code, 400), headers)

    @app.exception_handler(RecordingError)
    async def recording_error(request: Request, exc: RecordingError) -> JSONResponse:
        return _error(exc.code, str(exc), exc.status)

    @app.exception_handler(StoreError)
    async def store_error(request: Request, exc: StoreError) -> JSONResponse:
        # A malformed id is indistinguishable from an unknown one.
        return _error("not_found", "no session with this id for this token", 404)

    def openapi() -> dict:
        """FastAPI's schema, with its validation answers (422) documented as what the server
        sends: ErrorBody (``bad_request``), like every other error."""
        if app.openapi_schema is None:
            schema = get_openapi(
                title=app.title, version=app.version, description=app.description, routes=app.routes
            )
            ref = {"$ref": "#/components/schemas/ErrorBody"}
            for operation in (op for path in schema["paths"].values() for op in path.values()):
                answer = operation.get("responses", {}).get("422")
                if answer is not None and "HTTPValidationError" in json.dumps(answer):
                    operation["responses"]["422"] = {
                        "description": "`bad_request`: the body or query is malformed",
                        "content": {"application/json": {"schema": ref}},
                    }
            components = schema.get("components", {}).get("schemas", {})
            for unused in ("HTTPValidationError", "ValidationError"):
                components.pop(unused, None)
            app.openapi_schema = schema
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]

    @app.exception_handler(RequestValidationError)
    async def request_error(request: Request, exc: RequestValidationError) -> JSONResponse:
        """FastAPI's own validation, in the documented error form: an id that cannot be valid
        (a path parameter, or the body's ``room``) names nothing that exists (404 not_found, as
        an unknown id); any other malformed body or query is 422 bad_request, saying where."""
        errors = exc.errors()
        names_an_id = [
            e for e in errors if e.get("loc", ("",))[0] == "path" or e.get("loc")[-1:] == ("room",)
        ]
        if names_an_id:
            return _error("not_found", "nothing with this id", 404)
        where = "; ".join(
            f"{'.'.join(str(p) for p in e.get('loc', ()))}: {e.get('msg', 'invalid')}"
            for e in errors[:5]
        )
        return _error("bad_request", f"the request is malformed: {where}", 422)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        """Starlette's and the routes' own HTTP errors (an unknown path, a file not there), in
        the documented error form."""
        code = {404: "not_found", 405: "method_not_allowed", 401: "unauthorized"}.get(
            exc.status_code, f"http_{exc.status_code}"
        )
        return _error(code, str(exc.detail), exc.status_code, exc.headers)

    @app.exception_handler(MapError)
    async def map_error(request: Request, exc: MapError) -> JSONResponse:
        return _error("map_unavailable", str(exc), 409)

    @app.get("/healthz", tags=["server"])
    def health() -> dict:
        return {
            "status": "ok",
            "live_sessions": manager.live_count,
            "saved_sessions": manager.saved_count,
            "allocator": this_process_allocator(),  # what operators check when memory grows
        }

    return app


async def _reap(app: FastAPI) -> None:
    settings, manager = app.state.settings, app.state.manager
    while True:
        await asyncio.sleep(min(10.0, settings.session_ttl_s / 4))
        try:
            await asyncio.to_thread(
                manager.reap, settings.session_ttl_s, set(app.state.connections)
            )
        except Exception:  # one session's failure must not end the reaping of all others
            log.exception("reaping idle sessions failed; trying again")


def make_server(config: Config, app: FastAPI | None = None, **uvicorn_options) -> Server:
    """The uvicorn server for ``config`` (the app made from it unless given)."""
    settings = config.server
    server_config = uvicorn.Config(
        app or create_app(config),
        host=settings.host,
        port=settings.port,
        proxy_headers=True,
        forwarded_allow_ips=settings.forwarded_allow_ips,
        # No permessage-deflate: a frame is JPEG and zlib depth already, which deflate cannot
        # shrink, and deflating every frame again cost a phone's browser or the load tester
        # ~70 % of its CPU and the server as much again to inflate (issue 34).
        ws_per_message_deflate=False,
        **uvicorn_options,
    )
    return Server(server_config)


class Server(uvicorn.Server):
    """uvicorn's server, but a stop (SIGTERM, Ctrl-C) first tells every session's socket why it
    ends (``server_shutdown``, close 4007, as the protocol says) before uvicorn closes what is
    left with its generic 1012; the lifespan's shutdown then saves every session."""

    async def shutdown(self, sockets=None) -> None:
        await end_all_connections(self.config.app)
        await super().shutdown(sockets)
