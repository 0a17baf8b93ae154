"""``python -m server serve`` in a process of its own, for benchmarks and fault tests.

Started on a free loopback port with settings from ``DRONESIM_*`` variables; the constructor
returns once ``/healthz`` answers. Uses only the standard library (the load tester's rule).
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from collections.abc import Mapping
from contextlib import nullcontext
from pathlib import Path

# The folder that holds this ``server`` package: a checkout, or site-packages of an installed
# wheel. The child starts there, so ``python -m server`` runs the very code the caller imported.
IMPORT_ROOT = Path(__file__).resolve().parents[2]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def environment(assignments: list[str]) -> dict[str, str]:
    """``NAME=VALUE`` strings (a benchmark's ``--server-env``) -> an environment dict."""
    return dict(item.split("=", 1) for item in assignments)


def rss_mb(pid: int) -> float:
    """Resident memory of a process, MB (from /proc; NaN when it is gone)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return float("nan")


class ServerProcess:
    """A server process. env: extra environment (``DRONESIM_*`` settings); log: a file that
    gets its output (appended), or None to discard it."""

    def __init__(
        self,
        data_dir: Path,
        env: Mapping[str, str] | None = None,
        log: Path | None = None,
        timeout_s: float = 90.0,
    ) -> None:
        self.port = free_port()
        self.url, self.ws_url = f"http://127.0.0.1:{self.port}", f"ws://127.0.0.1:{self.port}"
        self.log = log
        # The child keeps its own copy of the log's descriptor; ours is closed at once.
        with log.open("ab") if log is not None else nullcontext(subprocess.DEVNULL) as out:
            self.proc = subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "server",
                    "serve",
                    "--port",
                    str(self.port),
                    "--data-dir",
                    str(Path(data_dir).resolve()),  # the child's working directory differs
                    "--no-demo",
                ],
                cwd=IMPORT_ROOT,
                env={**os.environ, **(env or {})},
                stdout=out,
                stderr=subprocess.STDOUT,
            )
        deadline = time.monotonic() + timeout_s
        while not self._healthy():
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.stop()
                tail = log.read_text(errors="replace")[-3000:] if log is not None else ""
                raise RuntimeError(f"server did not start; its log:\n{tail}")
            time.sleep(0.1)

    def _healthy(self) -> bool:
        try:
            with urllib.request.urlopen(f"{self.url}/healthz", timeout=1) as r:
                return r.status == 200
        except OSError:  # URLError and connection errors
            return False

    @property
    def pid(self) -> int:
        return self.proc.pid

    def rss_mb(self) -> float:
        return rss_mb(self.pid)

    def health(self) -> dict:
        """GET /healthz: live and saved sessions, the allocator."""
        with urllib.request.urlopen(f"{self.url}/healthz", timeout=30) as r:
            return json.loads(r.read())

    def create_session(self) -> tuple[str, str]:
        """POST /api/sessions -> (id, token)."""
        request = urllib.request.Request(f"{self.url}/api/sessions", method="POST")
        with urllib.request.urlopen(request, timeout=30) as r:
            body = json.loads(r.read())
        return body["id"], body["token"]

    def signal(self, sig: int, timeout_s: float = 60.0) -> int:
        """Send ``sig`` and wait for the exit status."""
        self.proc.send_signal(sig)
        return self.proc.wait(timeout_s)

    def terminate(self, timeout_s: float = 120.0) -> int:
        """SIGTERM (the server saves every session first) and wait."""
        return self.signal(signal.SIGTERM, timeout_s)

    def stop(self) -> None:
        """Kill it if it still runs."""
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(30)

    def __enter__(self) -> ServerProcess:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()
