"""Shared by every tier: the tiers themselves (the folder a test is in), CI's rule that nothing
skips, the real data beside the repo, small synthetic sequences, a live server, and the helpers
the tests of a session's conversation use (the browser's fixtures: tests/browser/conftest.py)."""

from __future__ import annotations

import asyncio
import os
import threading
import time
from collections.abc import Coroutine
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from server import protocol as P
from server.client.connection import Connection
from tests.support.paths import SHARED_DATA


def in_ci() -> bool:
    """CI=true (set by .ci/run): every test must run there."""
    return os.environ.get("CI", "").lower() in ("1", "true", "yes")


def missing(reason: str) -> None:
    """Skip a test whose data or tool is absent here; in CI (CI=true) that is a failure, as CI
    must run everything."""
    if in_ci():
        pytest.fail(f"required in CI: {reason}")
    pytest.skip(reason, allow_module_level=True)  # also for a module's missing import


def _fail_skip_in_ci(report) -> None:
    """In CI a skip of any kind (a skipif marker, an importorskip, a skip that bypassed
    ``missing``, a whole module's) is a failure too: a green CI run means every test ran."""
    if in_ci() and report.skipped and not hasattr(report, "wasxfail"):
        reason = report.longrepr[2] if isinstance(report.longrepr, tuple) else report.longrepr
        report.outcome = "failed"
        report.longrepr = f"skipped, and CI must run every test: {reason}"


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    _fail_skip_in_ci(outcome.get_result())


@pytest.hookimpl(hookwrapper=True)
def pytest_make_collect_report(collector):
    outcome = yield
    _fail_skip_in_ci(outcome.get_result())


# ---- tiers --------------------------------------------------------------------------------------
# Every test is in one tier, the folder under tests/ it is in, by what it needs; `pytest -m unit`
# (or server, browser, packaging) runs one, `pytest -m fast` the unit tests that take a second or
# two each (under two minutes in all on a 2-core machine), plain `pytest` everything:
#   unit       tests/unit/<package>/, as server/'s packages (tests/unit/ itself: server/'s own
#              modules): numerical stages, formats, the protocol, on slices of real data, in
#              this process
#   server     tests/server/: a real server or session process (live_server, or a test that
#              starts one, the command line or Ray)
#   browser    tests/browser/: a real Chromium (tests/browser/conftest.py's fixtures)
#   packaging  tests/packaging/: builds and installs the wheel, or checks the deployment files
# A unit module that tracks or fuses whole sequences says so with `pytestmark = pytest.mark.slow`
# (a single test with @pytest.mark.slow): unit, not fast.
TESTS = Path(__file__).resolve().parent
TIERS = {
    "unit": "numerical stages, formats and the protocol, in this process",
    "server": "a real server or session process on loopback",
    "browser": "a real Chromium driving the page",
    "packaging": "the wheel and the deployment files",
}


def tier_of(item) -> str:
    """The tier a collected test belongs to: the folder under tests/ it is in (see above)."""
    path = Path(item.path).resolve()
    folder = path.relative_to(TESTS).parts[0] if path.is_relative_to(TESTS) else None
    if folder not in TIERS:
        raise pytest.UsageError(
            f"{item.nodeid}: a test belongs in a tier's folder, tests/{{{','.join(TIERS)}}}/"
        )
    return folder


def pytest_configure(config):
    for name, what in (
        *TIERS.items(),
        ("fast", "the unit tests that take a second or two (under two minutes in all)"),
        ("slow", "a unit test that tracks or fuses whole sequences: not in the fast tier"),
    ):
        config.addinivalue_line("markers", f"{name}: {what}")


def pytest_collection_modifyitems(config, items):
    for item in items:
        tier = tier_of(item)
        item.add_marker(getattr(pytest.mark, tier))
        if tier == "unit" and item.get_closest_marker("slow") is None:
            item.add_marker(pytest.mark.fast)


def auth(token: str) -> dict:
    """The header that opens a session's REST resources."""
    return {"Authorization": f"Bearer {token}"}


def session_status(url: str, sid: str, token: str) -> dict:
    """GET /api/sessions/{sid} with its token -> the status."""
    import httpx

    return httpx.get(f"{url}/api/sessions/{sid}", headers=auth(token)).json()


def process_running(pid: int) -> bool:
    """A process that exists and is not a zombie waiting to be reaped."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def offline_track(ds, n: int) -> np.ndarray:
    """Poses from the tracker run in-process on the first n frames as the wire carries them."""
    from server import protocol as proto
    from server.registration import Tracker

    tracker = Tracker(ds.intrinsics)
    poses = []
    for i in range(n):
        f = ds[i]
        msg = proto.decode(proto.encode(proto.make_frame(i, f.timestamp, f.colour, f.depth)))
        hello = proto.make_hello("t", (1, 1, 1, 1), (f.colour.shape[1], f.colour.shape[0]))
        colour, depth = proto.decode_frame_images(msg, hello)
        poses.append(tracker.track(colour, depth).T_world_camera)
    return np.array(poses)


def random_pose(
    rng: np.random.Generator, max_angle_rad: float = 0.2, max_t_m: float = 0.1
) -> np.ndarray:
    """A random rigid transform with bounded rotation angle and translation."""
    from server.geometry import exp_se3

    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    xi = np.concatenate([axis * rng.uniform(0, max_angle_rad), rng.uniform(-max_t_m, max_t_m, 3)])
    return exp_se3(xi)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        missing(f"shared data folder {SHARED_DATA} is absent")
    return SHARED_DATA


@pytest.fixture(scope="session")
def demo_clean(tmp_path_factory) -> Path:
    """A small noise-free demo sequence (exact depth), generated once per test session."""
    from server.datasets.demo import DemoSpec, demo_sequence_path

    spec = DemoSpec(frames=24, noise=False)
    return demo_sequence_path(spec, cache_dir=tmp_path_factory.mktemp("demo"), progress=False)


@pytest.fixture(scope="module")
def demo_ready() -> Path:
    """The small demo preset (320x240, 90 frames) that the page's replays stream, generated once
    and cached (~/.cache/dronesim): a quarter of the full demo's work per frame."""
    from server.datasets.demo import demo_sequence_path
    from server.transport.routes_client import DEMO_PRESETS

    return demo_sequence_path(DEMO_PRESETS["small"], progress=False)


class LiveServer:
    """A real uvicorn server on a loopback port, in a background thread."""

    def __init__(
        self, data_dir: Path, simulation=None, registration=None, mapping=None, **settings
    ) -> None:
        import socket
        import threading

        from server.config import Config, ServerConfig
        from server.transport.app import create_app, make_server

        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            self.port = s.getsockname()[1]
        server = ServerConfig(host="127.0.0.1", port=self.port, data_dir=data_dir, **settings)
        # simulation: a SimulationConfig for the sessions' drones, registration: a
        # RegistrationConfig for their trackers, mapping: a MappingConfig for their maps
        # (default: the defaults)
        sections = {"simulation": simulation, "registration": registration, "mapping": mapping}
        self.config = Config(server=server, **{k: v for k, v in sections.items() if v is not None})
        self.settings = self.config.server
        self.app = create_app(self.config)
        self.server = make_server(
            self.config, self.app, log_level="warning", ws_max_size=64 * 2**20
        )
        self.thread = threading.Thread(target=self.server.run, daemon=True)
        self.thread.start()
        import time

        deadline = time.time() + 20
        while not self.server.started:
            if time.time() > deadline or not self.thread.is_alive():
                raise RuntimeError("server did not start")
            time.sleep(0.05)
        self.url = f"http://127.0.0.1:{self.port}"
        self.ws_url = f"ws://127.0.0.1:{self.port}"

    def create_session(self) -> tuple[str, str]:
        import httpx

        r = httpx.post(f"{self.url}/api/sessions")
        r.raise_for_status()
        body = r.json()
        return body["id"], body["token"]

    def stop(self) -> None:
        self.server.should_exit = True
        self.thread.join(timeout=60)


@pytest.fixture
def live_server(tmp_path):
    """live_server(data_dir=None, **settings) -> a server of the test's own, stopped after it.
    Without data_dir, the test's first server has tmp_path/"data" and each further one a data
    dir of its own: two servers running at once on one data dir is not a setup the server
    supports (a starting server waits for the session processes still writing there, see
    SessionStore.wait_for_writers)."""
    servers = []

    def start(data_dir: Path | None = None, **settings) -> LiveServer:
        if data_dir is None:
            data_dir = tmp_path / ("data" if not servers else f"data-{len(servers) + 1}")
        server = LiveServer(data_dir, **settings)
        servers.append(server)
        return server

    yield start
    for server in servers:
        server.stop()


UNASKED = {"map_chunk", "drone_state", "drone_event", "room"}  # what the server sends unasked


class Stream:
    """One session's conversation for tests (on the protocol client ``conn``): hello, then frames
    one at a time, each waiting for its pose."""

    def __init__(self, ws_url: str, sid: str, token: str, dataset) -> None:
        self.url, self.token = f"{ws_url}/ws/sessions/{sid}", token
        self.dataset = dataset
        self.poses: list[dict] = []
        self.map_points = 0  # total_points of the last map chunk
        self.surfaces: list[bool | None] = []  # each map chunk's surface
        self.conn: Connection | None = None

    async def open(self) -> Stream:
        """Connect and say hello (a socket of ours that the server still holds is taken over)."""
        K = self.dataset.intrinsics
        hello = P.make_hello("test", (K.fx, K.fy, K.cx, K.cy), (K.width, K.height))
        self.conn = await Connection.open(self.url, self.token, hello, timeout=60)
        return self

    async def answer(self) -> dict:
        while True:
            msg = await self.conn.receive(60)
            self.conn.acknowledge(msg)
            if msg["type"] == "map_chunk":
                self.map_points = msg["total_points"]
                self.surfaces.append(msg.get("surface"))
            if msg["type"] not in UNASKED:
                return msg

    async def send(
        self, seq: int, colour=None, depth=None, index: int | None = None, T_device_camera=None
    ) -> dict:
        """Frame ``index`` (default: seq) of the dataset, or the given images, as ``seq`` -> its
        pose; T_device_camera: the device's own pose to send with it (4x4), or None."""
        f = self.dataset[(seq if index is None else index) % len(self.dataset)]
        colour = f.colour if colour is None else colour
        depth = f.depth if depth is None else depth
        frame = P.make_frame(seq, f.timestamp, colour, depth, T_device_camera=T_device_camera)
        await self.conn.send_frame(frame)
        pose = await self.answer()
        assert pose["type"] == "pose" and pose["seq"] == seq, pose
        self.poses.append(pose)
        return pose

    async def send_range(self, seqs, first_index: int | None = None) -> None:
        """Frames ``seqs`` in turn; dataset frames from ``first_index`` on (default: the seqs)."""
        for k, seq in enumerate(seqs):
            await self.send(seq, index=None if first_index is None else first_index + k)

    async def close(self) -> None:
        await self.conn.close()

    def abort(self) -> None:
        """Drop the connection like a phone leaving the Wi-Fi: no close frame, no bye."""
        self.conn.abort()

    def matrices(self) -> np.ndarray:
        return np.array([P.pose_matrix(p) for p in self.poses])


class LoopThread:
    """An asyncio event loop in a helper thread, so that sync code (Playwright's sync API, which
    refuses to run inside an event loop) can hold a protocol client: ``run`` hands it a
    coroutine and blocks for the result. Leaving the ``with`` block cancels what still runs."""

    def __init__(self) -> None:
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()

    def run(self, coro: Coroutine[Any, Any, Any], timeout: float = 60.0) -> Any:
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout)

    def __enter__(self) -> LoopThread:
        return self

    def __exit__(self, *exc_info: object) -> None:
        async def cancel_the_rest() -> None:
            tasks = asyncio.all_tasks() - {asyncio.current_task()}
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)

        self.run(cancel_the_rest(), 10)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(10)
        self.loop.close()


class Updates:
    """Collects a session's updates (any thread) and waits for the ones a test expects."""

    def __init__(self) -> None:
        self.items: list = []
        self._cond = threading.Condition()

    def __call__(self, item) -> None:
        with self._cond:
            self.items.append(item)
            self._cond.notify_all()

    def wait_for(self, kind, n: int = 1, timeout_s: float = 60.0) -> list:
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while len(found := [i for i in self.items if isinstance(i, kind)]) < n:
                remaining = deadline - time.monotonic()
                assert remaining > 0, f"only {len(found)} {kind.__name__} of {n}: {self.items}"
                self._cond.wait(remaining)
            return found
