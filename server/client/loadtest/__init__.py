"""Load test: N phone-like clients at once, each with its own session, streaming one RGB-D sequence
through the shared protocol at a camera's pace; latency, throughput, drops and errors per session.

Each client creates a session (``POST /api/sessions``), opens its WebSocket, says hello and then
captures a frame every 1/fps seconds (the sessions' capture phases are spread over one frame
period, as real phones are not in step). A frame captured while ``max_in_flight`` frames await
an answer is dropped on the client, as a phone would. The sequence plays forward, then backward,
and so on, so that the camera motion stays continuous however long the run; each session starts
elsewhere in it, spread over one forward-and-back cycle (phones in a room are each at another
point of their walk), or all at its first frame with ``lockstep``. Frames are encoded
once before the run (JPEG colour, zlib or PNG depth), so the client's encoding stays out of the
measurement. Now and then a client sends a drone command (``hold``, or ``goto`` the drone's
spawn point once it has one). At the end each client waits for its last answers, says bye,
reads its session's statistics over REST and deletes the session (unless ``keep_sessions``).

Failures (a non-zero exit status of the CLI): HTTP errors, error messages from the server, an
unexpected close code, invalid server messages, frames never answered. One answer is tolerated:
``bad_command`` to a drone command while the server says the drone is not ready (yet).

Modules: ``sequence`` (frames encoded once, ping-pong order), ``client`` (one phone and the
run), ``report`` (numbers), ``table`` (the console view), ``plot`` (latency over time). The
protocol conversation itself is ``server.client.connection``.
"""

from server.client.loadtest.client import run_loadtest
from server.client.loadtest.plot import write_plot
from server.client.loadtest.report import build_report, live_line
from server.client.loadtest.results import LoadTestConfig, SessionResult
from server.client.loadtest.sequence import (
    FRAME_PROFILES,
    EncodedSequence,
    FrameProfile,
    LoadTestError,
    ping_pong_index,
)
from server.client.loadtest.table import report_footer, report_table

__all__ = [
    "FRAME_PROFILES",
    "EncodedSequence",
    "FrameProfile",
    "LoadTestConfig",
    "LoadTestError",
    "SessionResult",
    "build_report",
    "live_line",
    "ping_pong_index",
    "report_footer",
    "report_table",
    "run_loadtest",
    "write_plot",
]
