"""One load-test client (a phone: a session, its socket, a capture schedule, the answers) and the
run of many at once."""

from __future__ import annotations

import asyncio
import re
import time
from collections.abc import Callable

import websockets

from server import protocol as proto
from server.client import rest
from server.client.connection import NORMAL_CLOSE, ClientError, Connection, close_name
from server.client.loadtest.report import build_report
from server.client.loadtest.results import LoadTestConfig, SessionResult
from server.client.loadtest.sequence import EncodedSequence

# bad_command while the drone is not there yet: before the drone_event 'spawned' (or a first
# drone_state), or when the server's message says so after it.
_NOT_READY = re.compile(r"not (yet )?(available|ready|spawned)|\byet\b|no (map|drone)|spawn", re.I)


class _StartGate:
    """Every client starts capturing at the same moment, once all have connected (or failed)."""

    def __init__(self, clients: int) -> None:
        self.waiting, self.opened, self.t0 = clients, asyncio.Event(), 0.0

    def arrive(self) -> None:
        self.waiting -= 1
        if self.waiting == 0:
            self.t0 = time.monotonic() + 0.05
            self.opened.set()

    async def wait(self) -> float:
        """The common start time (monotonic seconds)."""
        self.arrive()
        await self.opened.wait()
        return self.t0


class _Client:
    """One phone: a session, its socket, a capture schedule and the answers."""

    def __init__(self, index: int, seq: EncodedSequence, cfg: LoadTestConfig, gate: _StartGate):
        self.seq, self.cfg, self.gate = seq, cfg, gate
        self.t0 = 0.0  # the common start, set when the gate opens
        self.arrived = False
        self.result = SessionResult(index)
        self.conn: Connection | None = None
        self.spawn: list[float] | None = None  # the drone's first position, world metres
        self.command_id = 0
        self.context = rest.ssl_context(cfg.url, cfg.insecure)

    async def run(self, phase_s: float) -> SessionResult:
        try:
            return await self._run(phase_s)
        finally:
            if not self.arrived:  # failed before streaming: do not hold the others back
                self.gate.arrive()

    async def _rest(self, method: str, url: str, token: str | None, ok: tuple[int, ...]):
        """The JSON body ({} when empty), or None after recording the failure."""
        status, body = await asyncio.to_thread(rest.request, method, url, token, self.context)
        if status not in ok:
            said = "unreachable" if status == 0 else f"HTTP {status}"
            self.result.failures.append(f"{method} {url.split('/api/')[-1]}: {said}")
            return None
        return body or {}

    async def _run(self, phase_s: float) -> SessionResult:
        r, base = self.result, self.cfg.url
        body = await self._rest("POST", rest.sessions_url(base), None, ok=(200, 201))
        if body is None:
            return r
        r.id, token = body["id"], body["token"]
        try:
            self.conn = await Connection.connect(
                rest.websocket_url(base, r.id), token, ssl=self.context
            )
            async with self.conn:
                await self._stream(self.conn, phase_s)
        except websockets.InvalidHandshake as exc:
            status = getattr(getattr(exc, "response", None), "status_code", None)
            status = status or getattr(exc, "status_code", "?")  # websockets < 14
            r.failures.append(f"websocket refused: HTTP {status}")
        except websockets.ConnectionClosed as exc:
            r.close_code = exc.rcvd.code if exc.rcvd else None
            r.failures.append(f"connection closed early ({close_name(r.close_code)})")
        except ClientError as exc:
            r.failures.append(str(exc))
        except proto.ProtocolError as exc:
            r.failures.append(f"invalid server message: {exc}")
        except (OSError, asyncio.TimeoutError) as exc:
            r.failures.append(f"websocket: {type(exc).__name__} {exc}")
        if self.conn is not None:
            r.failures.extend(f"invalid server message: {e}" for e in self.conn.invalid)
            if self.conn.failure is not None:
                r.failures.append(f"client failed: {self.conn.failure}")
            r.unanswered = len(self.conn.in_flight)
        if r.unanswered:
            r.failures.append(f"{r.unanswered} frames never answered")
        session_url = rest.sessions_url(base, r.id)
        status = await self._rest("GET", session_url, token, ok=(200,))
        if status:
            r.server_status = {
                k: status.get(k)
                for k in (
                    "frames_received",
                    "frames_processed",
                    "frames_dropped",
                    "fusion_skipped",
                    "device_pose",
                    "loops",  # what the session's loop closure did (null: not running)
                    "recovery",  # tracking recovery: relocalised, segments, merged, ...
                )
            }
            r.server_dropped = max(r.server_dropped, status.get("frames_dropped") or 0)
        if not self.cfg.keep_sessions:
            await self._rest("DELETE", session_url, token, ok=(204,))
        return r

    async def _stream(self, conn: Connection, phase_s: float) -> None:
        r, cfg, seq = self.result, self.cfg, self.seq
        hello = proto.make_hello(
            f"{cfg.client_name}/{r.index}",
            seq.intrinsics,
            seq.size,
            seq.depth_size,
            depth_scale=1000.0,
        )
        welcome = await conn.hello(hello, cfg.grace_s)
        max_in_flight = min(cfg.max_in_flight, welcome["max_in_flight"])
        conn.start(self._handle)
        self.arrived = True
        self.t0 = await self.gate.wait()
        start = self.t0 + phase_s
        stop = start + cfg.duration_s
        next_command = start + cfg.command_every_s / 2
        first = 0 if cfg.lockstep else seq.start(r.index, cfg.sessions)
        k = 0
        while (due := start + k / cfg.fps) < stop and conn.receiving:
            await asyncio.sleep(max(0.0, due - time.monotonic()))
            r.captured += 1
            if len(conn.in_flight) >= max_in_flight:
                r.client_dropped += 1
            else:
                frame = {"type": "frame", **seq.frames[seq.index(first + k)], "seq": k}
                sent_at = await conn.send_frame({**frame, "timestamp": due - self.t0})
                r.send_lag_ms.append((sent_at - due) * 1e3)
                r.sent += 1
            if cfg.command_every_s > 0 and time.monotonic() >= next_command:
                await conn.send(self._next_command())
                r.commands_sent += 1
                next_command += cfg.command_every_s
            k += 1
        # The last answers (bounded), then bye; the server closes with 1000.
        await conn.drain(cfg.grace_s)
        try:
            await conn.bye("load test done", cfg.grace_s)
        except asyncio.TimeoutError:
            r.failures.append("no close from the server after bye")
        r.close_code = conn.close_code
        if r.close_code != NORMAL_CLOSE:
            r.failures.append(f"unexpected {close_name(r.close_code)}")

    def _next_command(self) -> dict:
        """hold and goto (the drone's spawn point: free space, so reachable) in turn."""
        self.command_id += 1
        if self.spawn is not None and self.command_id % 2 == 0:
            return proto.make_command(self.command_id, "goto", target=self.spawn)
        return proto.make_command(self.command_id, "hold")

    def _handle(self, msg: dict, latency_ms: float | None) -> None:
        """One server message (the connection has already updated the window)."""
        r, kind = self.result, msg["type"]
        if kind == "pose":
            if latency_ms is not None:
                r.latency.append((time.monotonic() - self.t0, latency_ms))
            r.processed += 1
            r.states[msg["state"]] += 1
            if msg.get("recovery"):
                r.recoveries[msg["recovery"]] += 1
            r.server_dropped = max(r.server_dropped, msg["dropped"])
            for stage, ms in msg["timings_ms"].items():
                r.stages_ms.setdefault(stage, []).append(ms)
        elif kind == "map_chunk":
            r.map_points += msg["count"]
        elif kind == "drone_state":
            r.drone_states += 1
            if self.spawn is None:
                self.spawn = [float(v) for v in proto.pose_matrix(msg, "T_world_drone")[:3, 3]]
        elif kind == "map_corrected":
            # A loop closure moved the world: the spawn point, a place in the old world, is
            # where T_correction puts it in the new one (the server reads targets there).
            if self.spawn is not None:
                T, _ = proto.decode_map_corrected(msg)
                self.spawn = [float(v) for v in T[:3, :3] @ self.spawn + T[:3, 3]]
        elif kind == "drone_event":
            r.drone_events[msg["event"]] += 1
            if msg["event"] == "spawned" and self.spawn is None:
                self.spawn = [float(v) for v in msg["position"]]
        elif kind == "error":
            r.errors[msg["name"]] += 1
            if msg["name"] == "bad_command" and (
                self.spawn is None or _NOT_READY.search(msg["message"])
            ):
                r.commands_not_ready += 1
            else:
                r.failures.append(f"error {msg['code']} {msg['name']}: {msg['message']}")


# ---- the run ------------------------------------------------------------------------------------


async def run_loadtest(
    seq: EncodedSequence,
    cfg: LoadTestConfig,
    on_progress: Callable[[list[SessionResult], float], None] | None = None,
    progress_every_s: float = 0.5,
) -> dict:
    """Run ``cfg.sessions`` clients at once; returns the report (see ``build_report``)."""
    t_zero = time.monotonic()
    cpu_zero = time.process_time()
    gate = _StartGate(cfg.sessions)
    clients = [_Client(i, seq, cfg, gate) for i in range(cfg.sessions)]
    phases = [i / (cfg.sessions * cfg.fps) for i in range(cfg.sessions)]  # spread over a period
    tasks = [asyncio.create_task(c.run(phase)) for c, phase in zip(clients, phases, strict=True)]
    while on_progress is not None and not all(t.done() for t in tasks):
        elapsed = time.monotonic() - gate.t0 if gate.opened.is_set() else 0.0
        on_progress([c.result for c in clients], max(0.0, elapsed))
        await asyncio.wait(tasks, timeout=progress_every_s)
    results = await asyncio.gather(*tasks)
    wall = time.monotonic() - t_zero
    return build_report(
        results,
        cfg,
        seq,
        wall_s=wall,
        client_cpu_percent=100 * (time.process_time() - cpu_zero) / wall,
    )
