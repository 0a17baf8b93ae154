"""The load test's inputs (``LoadTestConfig``) and what each client saw (``SessionResult``)."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field


@dataclass
class LoadTestConfig:
    url: str = "http://127.0.0.1:8000"  # the server's base URL (http or https)
    sessions: int = 4
    fps: float = 15.0
    duration_s: float = 30.0  # capture time per session
    max_in_flight: int = 2  # the welcome's value when smaller
    command_every_s: float = 2.0  # drone command period per session; 0: none
    # Every session plays the same frame at once (a worst case: the sequence's hard stretches
    # reach every session together); else each starts elsewhere (EncodedSequence.start).
    lockstep: bool = False
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
    recoveries: Counter = field(default_factory=Counter)  # poses by their `recovery`
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
