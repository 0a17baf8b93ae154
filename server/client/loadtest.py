"""Load test: N phone-like clients at once, each with its own session, streaming one RGB-D sequence
through the shared protocol at a camera's pace; latency, throughput, drops and errors per session.

Each client creates a session (``POST /api/sessions``), opens its WebSocket, says hello and then
captures a frame every 1/fps seconds (the sessions' capture phases are spread over one frame
period, as real phones are not in step). A frame captured while ``max_in_flight`` frames await
an answer is dropped on the client, as a phone would. The sequence plays forward, then backward,
and so on, so that the camera motion stays continuous however long the run. Frames are encoded
once before the run (JPEG colour, zlib or PNG depth), so the client's encoding stays out of the
measurement. Now and then a client sends a drone command (``hold``, or ``goto`` the drone's
spawn point once it has one). At the end each client waits for its last answers, says bye,
reads its session's statistics over REST and deletes the session (unless ``keep_sessions``).

Failures (a non-zero exit status of the CLI): HTTP errors, error messages from the server, an
unexpected close code, invalid server messages, frames never answered. One answer is tolerated:
``bad_command`` to a drone command while the server says the drone is not ready (yet).
"""

from __future__ import annotations

import asyncio
import json
import logging
import re
import ssl as ssl_module
import time
import urllib.error
import urllib.request
from collections import Counter
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
import websockets

from server import protocol as proto
from server.client.replay import await_answers
from server.datasets import RGBDDataset
from server.errors import DroneSimError

log = logging.getLogger(__name__)

# bad_command while the drone is not there yet: before the drone_event 'spawned' (or a first
# drone_state), or when the server's message says so after it.
_NOT_READY = re.compile(r"not (yet )?(available|ready|spawned)|\byet\b|no (map|drone)|spawn", re.I)
_CLOSE_NAMES = {code: name for name, code in proto.CLOSE_CODES.items()}
HTTP_TIMEOUT_S = 30.0


class LoadTestError(DroneSimError):
    """The load test could not run at all (e.g. an empty sequence)."""


def ping_pong_index(k: int, n: int) -> int:
    """Which of n frames capture k shows when a sequence plays forward, backward, forward, ...
    (looping that way keeps the camera's motion continuous)."""
    if n == 1:
        return 0
    k %= 2 * n - 2
    return k if k < n else 2 * n - 2 - k


@dataclass
class EncodedSequence:
    """A sequence encoded once for the wire: frame messages without seq and timestamp."""

    name: str
    intrinsics: tuple[float, float, float, float]  # fx, fy, cx, cy of the colour image, px
    size: tuple[int, int]  # width, height, px (colour and depth)
    frames: list[dict]

    @classmethod
    def from_dataset(
        cls,
        dataset: RGBDDataset,
        max_frames: int | None = None,
        depth_format: str = "zlib",
        workers: int = 4,
    ) -> EncodedSequence:
        n = len(dataset) if max_frames is None else min(max_frames, len(dataset))
        if n < 1:
            raise LoadTestError(f"{dataset.name} has no frames to stream")

        def encode(i: int) -> dict:
            frame = dataset[i]
            message = proto.make_frame(0, 0.0, frame.colour, frame.depth, depth_format=depth_format)
            del message["seq"], message["timestamp"]
            return message

        with ThreadPoolExecutor(workers) as pool:  # OpenCV releases the GIL while encoding
            frames = list(pool.map(encode, range(n)))
        K = dataset.intrinsics
        return cls(dataset.name, (K.fx, K.fy, K.cx, K.cy), (K.width, K.height), frames)

    def index(self, k: int) -> int:
        """Frame of capture k when playing forward, backward, forward, ... (ping-pong)."""
        return ping_pong_index(k, len(self.frames))

    @property
    def mean_bytes(self) -> float:
        return float(np.mean([len(f["colour"]) + len(f["depth"]) for f in self.frames]))


@dataclass
class LoadTestConfig:
    url: str = "http://127.0.0.1:8000"  # the server's base URL (http or https)
    sessions: int = 4
    fps: float = 15.0
    duration_s: float = 30.0  # capture time per session
    max_in_flight: int = 2  # the welcome's value when smaller
    command_every_s: float = 2.0  # drone command period per session; 0: none
    grace_s: float = 10.0  # wait this long for the last answers, then for the close
    keep_sessions: bool = False  # leave the sessions on the server (else DELETE them)
    insecure: bool = False  # accept any TLS certificate (the server's self-signed one)
    client_name: str = "loadtest"


@dataclass
class SessionResult:
    """What one client saw. Times: seconds since the run started; latencies: milliseconds."""

    index: int
    id: str | None = None
    captured: int = 0  # frames the camera produced
    sent: int = 0
    client_dropped: int = 0  # captured while max_in_flight frames awaited answers
    processed: int = 0  # poses received
    server_dropped: int = 0  # pose.dropped, or the session's frames_dropped when read at the end
    unanswered: int = 0  # still in flight after the grace period
    latency: list[tuple[float, float]] = field(default_factory=list)  # (t, send-to-pose ms)
    send_lag_ms: list[float] = field(default_factory=list)  # send time after the capture time
    states: Counter = field(default_factory=Counter)
    stages_ms: dict[str, list[float]] = field(default_factory=dict)
    errors: Counter = field(default_factory=Counter)  # error messages by name
    failures: list[str] = field(default_factory=list)
    commands_sent: int = 0
    commands_not_ready: int = 0  # bad_command: the drone is not ready (tolerated)
    drone_states: int = 0
    drone_events: Counter = field(default_factory=Counter)
    map_points: int = 0
    close_code: int | None = None
    server_status: dict | None = None


# ---- HTTP ---------------------------------------------------------------------------------------


def _ssl_context(url: str, insecure: bool) -> ssl_module.SSLContext | None:
    if not url.startswith(("https", "wss")):
        return None
    context = ssl_module.create_default_context()
    if insecure:
        context.check_hostname, context.verify_mode = False, ssl_module.CERT_NONE
    return context


def _http(method: str, url: str, token: str | None, context) -> tuple[int, dict | None]:
    """(status, JSON body or None); 0 when the server cannot be reached."""
    request = urllib.request.Request(url, method=method)
    if token is not None:
        request.add_header("Authorization", f"Bearer {token}")
    try:
        with urllib.request.urlopen(request, timeout=HTTP_TIMEOUT_S, context=context) as response:
            body = response.read()
            return response.status, json.loads(body) if body else None
    except urllib.error.HTTPError as exc:
        return exc.code, None
    except (urllib.error.URLError, OSError) as exc:
        log.warning("%s %s: %s", method, url, exc)
        return 0, None


async def _rest(
    result: SessionResult, method: str, url: str, token: str | None, context, ok: tuple[int, ...]
) -> dict | None:
    status, body = await asyncio.to_thread(_http, method, url, token, context)
    if status not in ok:
        result.failures.append(
            f"{method} {url.split('/api/')[-1]}: "
            f"{'unreachable' if status == 0 else f'HTTP {status}'}"
        )
        return None
    return body or {}


# ---- one client ---------------------------------------------------------------------------------


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
        self.in_flight: dict[int, float] = {}  # seq -> monotonic send time
        self.answered = asyncio.Event()
        self.spawn: list[float] | None = None  # the drone's first position, world metres
        self.command_id = 0
        self.context = _ssl_context(cfg.url, cfg.insecure)

    async def run(self, phase_s: float) -> SessionResult:
        try:
            return await self._run(phase_s)
        finally:
            if not self.arrived:  # failed before streaming: do not hold the others back
                self.gate.arrive()

    async def _run(self, phase_s: float) -> SessionResult:
        r, base = self.result, self.cfg.url.rstrip("/")
        body = await _rest(r, "POST", f"{base}/api/sessions", None, self.context, ok=(200, 201))
        if body is None:
            return r
        r.id, token = body["id"], body["token"]
        ws_base = base.replace("http", "ws", 1)
        try:
            async with websockets.connect(
                f"{ws_base}/ws/sessions/{r.id}?token={token}", max_size=None, ssl=self.context
            ) as ws:
                await self._stream(ws, phase_s)
        except websockets.InvalidHandshake as exc:
            status = getattr(getattr(exc, "response", None), "status_code", None)
            status = status or getattr(exc, "status_code", "?")  # websockets < 14
            r.failures.append(f"websocket refused: HTTP {status}")
        except websockets.ConnectionClosed as exc:
            r.close_code = exc.rcvd.code if exc.rcvd else None
            r.failures.append(f"connection closed early ({self._close_name(r.close_code)})")
        except proto.ProtocolError as exc:
            r.failures.append(f"invalid server message: {exc}")
        except (OSError, asyncio.TimeoutError) as exc:
            r.failures.append(f"websocket: {type(exc).__name__} {exc}")
        r.unanswered = len(self.in_flight)
        if r.unanswered:
            r.failures.append(f"{r.unanswered} frames never answered")
        session_url = f"{base}/api/sessions/{r.id}"
        status = await _rest(r, "GET", session_url, token, self.context, ok=(200,))
        if status:
            r.server_status = {
                k: status.get(k)
                for k in ("frames_received", "frames_processed", "frames_dropped", "fusion_skipped")
            }
            r.server_dropped = max(r.server_dropped, status.get("frames_dropped") or 0)
        if not self.cfg.keep_sessions:
            await _rest(r, "DELETE", session_url, token, self.context, ok=(204,))
        return r

    @staticmethod
    def _close_name(code: int | None) -> str:
        return f"close {code} {_CLOSE_NAMES.get(code, '')}".strip() if code else "no close frame"

    async def _stream(self, ws, phase_s: float) -> None:
        r, cfg, seq = self.result, self.cfg, self.seq
        (fx, fy, cx, cy), size = seq.intrinsics, seq.size
        hello = proto.make_hello(
            f"{cfg.client_name}/{r.index}", (fx, fy, cx, cy), size, depth_scale=1000.0
        )
        await ws.send(proto.encode(hello))
        welcome = proto.decode(await asyncio.wait_for(ws.recv(), cfg.grace_s))
        if welcome["type"] != "welcome":
            said = f" {welcome['name']}: {welcome['message']}" if welcome["type"] == "error" else ""
            r.failures.append(f"expected welcome, got {welcome['type']}{said}")
            return
        max_in_flight = min(cfg.max_in_flight, welcome["max_in_flight"])
        receiver = asyncio.create_task(self._receive(ws))
        self.arrived = True
        self.t0 = await self.gate.wait()
        start = self.t0 + phase_s
        stop = start + cfg.duration_s
        next_command = start + cfg.command_every_s / 2
        k = 0
        while (due := start + k / cfg.fps) < stop and not receiver.done():
            await asyncio.sleep(max(0.0, due - time.monotonic()))
            r.captured += 1
            if len(self.in_flight) >= max_in_flight:
                r.client_dropped += 1
            else:
                data = proto.encode(
                    {
                        "type": "frame",
                        **seq.frames[seq.index(k)],
                        "seq": k,
                        "timestamp": due - self.t0,
                    }
                )
                now = time.monotonic()
                r.send_lag_ms.append((now - due) * 1e3)
                self.in_flight[k] = now
                await ws.send(data)
                r.sent += 1
            if cfg.command_every_s > 0 and time.monotonic() >= next_command:
                await ws.send(proto.encode(self._next_command()))
                r.commands_sent += 1
                next_command += cfg.command_every_s
            k += 1
        # The last answers (bounded), then bye; the server closes with 1000.
        await await_answers(
            self.in_flight, self.answered, time.monotonic() + cfg.grace_s, receiver.done
        )
        if not receiver.done():
            await ws.send(proto.encode(proto.make_bye("load test done")))
        try:
            await asyncio.wait_for(receiver, cfg.grace_s)
        except asyncio.TimeoutError:
            r.failures.append("no close from the server after bye")
        r.close_code = ws.close_code
        if r.close_code != 1000:
            r.failures.append(f"unexpected {self._close_name(r.close_code)}")

    def _next_command(self) -> dict:
        """hold and goto (the drone's spawn point: free space, so reachable) in turn."""
        self.command_id += 1
        if self.spawn is not None and self.command_id % 2 == 0:
            return proto.make_command(self.command_id, "goto", target=self.spawn)
        return proto.make_command(self.command_id, "hold")

    async def _receive(self, ws) -> None:
        r = self.result
        try:
            async for data in ws:
                try:
                    msg = proto.decode(data, direction=proto.SERVER_TO_CLIENT)
                except proto.ProtocolError as exc:
                    r.failures.append(f"invalid server message: {exc}")
                    continue
                self._handle(msg)
        except websockets.ConnectionClosed:
            pass  # the close code is read by the caller

    def _handle(self, msg: dict) -> None:
        r, kind, now = self.result, msg["type"], time.monotonic()
        if kind == "pose":
            sent_at = self.in_flight.get(msg["seq"])
            if sent_at is not None:
                r.latency.append((now - self.t0, (now - sent_at) * 1e3))
            self._acknowledge(msg["seq"])
            r.processed += 1
            r.states[msg["state"]] += 1
            r.server_dropped = max(r.server_dropped, msg["dropped"])
            for stage, ms in msg["timings_ms"].items():
                r.stages_ms.setdefault(stage, []).append(ms)
        elif kind == "map_chunk":
            r.map_points += msg["count"]
        elif kind == "drone_state":
            r.drone_states += 1
            if self.spawn is None:
                self.spawn = [float(v) for v in proto.pose_matrix(msg, "T_world_drone")[:3, 3]]
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
            if msg.get("seq") is not None:
                self._acknowledge(msg["seq"])
        self.answered.set()

    def _acknowledge(self, seq: int) -> None:
        """One answer acknowledges every frame with a seq up to its own."""
        for s in [s for s in self.in_flight if s <= seq]:
            del self.in_flight[s]


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


def _percentiles(values) -> dict:
    v = np.asarray(values, dtype=float)
    if not len(v):
        return {"p50_ms": None, "p95_ms": None, "p99_ms": None, "mean_ms": None, "max_ms": None}
    p50, p95, p99 = np.percentile(v, [50, 95, 99])
    return {
        "p50_ms": float(p50),
        "p95_ms": float(p95),
        "p99_ms": float(p99),
        "mean_ms": float(v.mean()),
        "max_ms": float(v.max()),
    }


def _rates(
    captured: int,
    sent: int,
    processed: int,
    client_dropped: int,
    server_dropped: int,
    duration_s: float,
) -> dict:
    return {
        "processed_fps": processed / duration_s,
        "client_drop_rate": client_dropped / captured if captured else 0.0,
        "server_drop_rate": server_dropped / sent if sent else 0.0,
        # Every captured frame without a pose: dropped on either side, refused or unanswered.
        "drop_rate": 1 - processed / captured if captured else 0.0,
    }


def _session_report(r: SessionResult, duration_s: float) -> dict:
    return {
        "index": r.index,
        "id": r.id,
        "captured": r.captured,
        "sent": r.sent,
        "processed": r.processed,
        "client_dropped": r.client_dropped,
        "server_dropped": r.server_dropped,
        "unanswered": r.unanswered,
        **_rates(r.captured, r.sent, r.processed, r.client_dropped, r.server_dropped, duration_s),
        "latency": _percentiles([ms for _, ms in r.latency]),
        "send_lag_p95_ms": float(np.percentile(r.send_lag_ms, 95)) if r.send_lag_ms else None,
        "states": dict(r.states),
        "errors": dict(r.errors),
        "failures": r.failures,
        "commands": {
            "sent": r.commands_sent,
            "not_ready": r.commands_not_ready,
            "drone_states": r.drone_states,
            "drone_events": dict(r.drone_events),
        },
        "map_points": r.map_points,
        "close_code": r.close_code,
        "server_status": r.server_status,
    }


def build_report(
    results: list[SessionResult],
    cfg: LoadTestConfig,
    seq: EncodedSequence,
    wall_s: float,
    client_cpu_percent: float,
) -> dict:
    """Per session and total: counts, rates, latency percentiles, server stage times, failures;
    plus each session's latency timeline [[t_s, ms], ...] for plots."""
    d = cfg.duration_s
    totals = {
        k: sum(getattr(r, k) for r in results)
        for k in ("captured", "sent", "processed", "client_dropped", "server_dropped", "unanswered")
    }
    stages: dict[str, list[float]] = {}
    for r in results:
        for stage, values in r.stages_ms.items():
            stages.setdefault(stage, []).extend(values)
    errors = sum((r.errors for r in results), Counter())
    return {
        "config": {
            **cfg.__dict__,
            "dataset": seq.name,
            "frames": len(seq.frames),
            "size": list(seq.size),
            "mean_frame_bytes": seq.mean_bytes,
        },
        "wall_s": wall_s,
        "client_cpu_percent": client_cpu_percent,
        "total": {
            **totals,
            **_rates(
                totals["captured"],
                totals["sent"],
                totals["processed"],
                totals["client_dropped"],
                totals["server_dropped"],
                d,
            ),
            "processed_fps_per_session": totals["processed"] / d / max(1, len(results)),
            "latency": _percentiles([ms for r in results for _, ms in r.latency]),
            "errors": dict(errors),
            "failures": sum(len(r.failures) for r in results),
        },
        "stages_ms": {
            k: {
                "median": float(np.median(v)),
                "p95": float(np.percentile(v, 95)),
                "mean": float(np.mean(v)),
            }
            for k, v in sorted(stages.items())
        },
        "sessions": [_session_report(r, d) for r in results],
        "timeline": [[[round(t, 4), round(ms, 3)] for t, ms in r.latency] for r in results],
    }


def live_line(results: list[SessionResult], elapsed_s: float) -> str:
    """One line of progress: poses/s, p95 so far, drops and errors over all sessions."""
    latencies = [ms for r in results for _, ms in r.latency]
    p95 = f"{np.percentile(latencies, 95):.0f} ms" if latencies else "-"
    captured = sum(r.captured for r in results) or 1
    return (
        f"{sum(r.id is not None for r in results)} sessions | "
        f"{sum(r.processed for r in results) / max(elapsed_s, 1e-3):.1f} poses/s | p95 {p95} | "
        f"client drops {100 * sum(r.client_dropped for r in results) / captured:.1f}% | "
        f"server drops {sum(r.server_dropped for r in results)} | "
        f"failures {sum(len(r.failures) for r in results)}"
    )


# ---- presentation -------------------------------------------------------------------------------


def _ms(value: float | None) -> str:
    return "-" if value is None else f"{value:.0f}"


def report_table(report: dict):
    """A rich table: one row per session and a total row. Errors: those counted as failures."""
    from rich import box
    from rich.table import Table

    c, t = report["config"], report["total"]
    table = Table(
        title=f"{c['sessions']} sessions x {c['fps']:g} fps x {c['duration_s']:g} s, "
        f"{c['dataset']} {c['size'][0]}x{c['size'][1]}: latency ms, drops",
        box=box.SIMPLE_HEAD,
        pad_edge=False,
        padding=(0, 1),
        collapse_padding=True,
    )
    # Latency (ms) send to pose; drops: on the client, on the server; err: failures.
    for col in (
        "sess",
        "sent",
        "poses",
        "pose/s",
        "drop c",
        "drop s",
        "p50",
        "p95",
        "p99",
        "ok/wk/lost",
        "err",
    ):
        table.add_column(col, justify="right")

    def row(name: str, s: dict, states: str, errors: int, style=None) -> None:
        table.add_row(
            name,
            str(s["sent"]),
            str(s["processed"]),
            f"{s['processed_fps']:.1f}",
            f"{100 * s['client_drop_rate']:.1f}%",
            f"{100 * s['server_drop_rate']:.1f}%",
            _ms(s["latency"]["p50_ms"]),
            _ms(s["latency"]["p95_ms"]),
            _ms(s["latency"]["p99_ms"]),
            states,
            str(errors),
            style=style,
        )

    for s in report["sessions"]:
        st = s["states"]
        row(
            str(s["index"]),
            s,
            f"{st.get('ok', 0)}/{st.get('weak', 0)}/{st.get('lost', 0)}",
            len(s["failures"]),
        )
    row("all", t, "", t["failures"], style="bold")
    return table


def report_footer(report: dict) -> str:
    """Stage times, drop rate against capture, client CPU and command answers in a few lines."""
    stages = ", ".join(
        f"{k} {v['median']:.1f}"
        for k, v in report["stages_ms"].items()
        if not k.startswith("track_")
    )
    commands = [s["commands"] for s in report["sessions"]]
    lags = [s["send_lag_p95_ms"] for s in report["sessions"] if s["send_lag_p95_ms"] is not None]
    t = report["total"]
    return (
        f"server stages, median ms: {stages or '-'}\n"
        f"frames captured {t['captured']}, without a pose {100 * t['drop_rate']:.1f}%; "
        f"client CPU {report['client_cpu_percent']:.0f}% of one core, "
        f"capture-to-send lag p95 {max(lags, default=0):.1f} ms\n"
        f"drone commands sent {sum(c['sent'] for c in commands)}, answered 'not ready' "
        f"{sum(c['not_ready'] for c in commands)} (tolerated), drone_state messages "
        f"{sum(c['drone_states'] for c in commands)}; errors by name: "
        f"{', '.join(f'{k} {v}' for k, v in report['total']['errors'].items()) or 'none'}"
    )


def write_plot(report: dict, path) -> None:
    """Latency over time (every pose, per session, with the rolling p95) and poses per second."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    c = report["config"]
    fig, (ax, ax_rate) = plt.subplots(
        2, 1, figsize=(10, 6.5), sharex=True, gridspec_kw={"height_ratios": [3, 1]}
    )
    everything = []
    for i, timeline in enumerate(report["timeline"]):
        if timeline:
            t, ms = np.asarray(timeline).T
            ax.scatter(t, ms, s=4, alpha=0.6, label=f"session {i}")
            everything.append(np.asarray(timeline))
    if everything:
        t, ms = np.concatenate(everything).T
        bins = np.arange(0.0, max(c["duration_s"], t.max()) + 1.0, 1.0)
        which = np.digitize(t, bins)
        centres = [bins[b - 1] + 0.5 for b in np.unique(which)]
        p95 = [np.percentile(ms[which == b], 95) for b in np.unique(which)]
        ax.plot(centres, p95, "k-", lw=1.5, label="p95 per second, all sessions")
        ax_rate.bar(bins[:-1] + 0.5, np.histogram(t, bins)[0], width=0.9, color="tab:gray")
    ax.set_ylim(bottom=0)
    ax.set_ylabel("send to pose, ms")
    ax.set_title(
        f"{c['sessions']} sessions x {c['fps']:g} fps, {c['dataset']}: "
        f"p95 {_ms(report['total']['latency']['p95_ms'])} ms"
    )
    ax.grid(alpha=0.3)
    if len(everything) <= 10:
        ax.legend(loc="upper right", fontsize=7, markerscale=3)
    ax_rate.axhline(c["sessions"] * c["fps"], color="tab:red", lw=1, label="captured per second")
    ax_rate.set_ylabel("poses / s")
    ax_rate.set_xlabel("time since start, s")
    ax_rate.legend(loc="lower right", fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
