"""Sessions as Ray actors (``serve --ray ADDRESS``) on a local two-node Ray cluster, its traffic
on the loopback only: sessions land on both nodes, poses flow, a second front-end takes a
session's socket over, a restarted front-end finds the live sessions again, a delete ends the
actor; each actor runs its session in a worker and a mapper process of its own, whose death
fails the session as under the process workers; a shared room runs on its owner's node with one
map, which serves a joined phone past its owner's end and ends after it.

One module-scoped cluster (two nodes of two CPUs each: a room's owner and a phone fit on one);
the front-ends are real uvicorn servers in this process, sharing its Ray driver connection (as
separate processes they would each have one).
"""

from __future__ import annotations

import asyncio
import gc
import os
import shutil
import signal
import tempfile
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
import websockets

from tests.conftest import LiveServer, Stream, auth, missing, process_running, session_status
from tests.support.rest import CREATE_TIMEOUT_S, create_session, map_caught_up, wait_for_status

# Ray's processes then use 127.0.0.1 for their node address and sockets (see NOTES-ray.md);
# read when Ray's constants are imported, so before the first ``import ray``.
os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"
try:
    import ray
    from ray.cluster_utils import Cluster
except ImportError:
    missing("ray is not installed (pip install -e '.[ray]'; it is in [dev])")


from server import protocol as P  # noqa: E402
from server.datasets import open_dataset  # noqa: E402
from tests.server.test_shared_rooms_server import _stream  # noqa: E402

NAMESPACE = "dronesim"


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    from ray._private import ray_constants

    ray_constants.ENABLE_RAY_CLUSTER = False  # in case ray was imported before the env was set
    # Ray's files (sockets, logs, its "current cluster" address file) in a folder of this test's
    # own, short enough for Unix socket paths: a leftover /tmp/ray must not be joined or touched.
    temp = tempfile.mkdtemp(prefix="rt", dir="/tmp")
    saved = os.environ.get("RAY_TMPDIR")
    os.environ["RAY_TMPDIR"] = temp
    cluster = Cluster(
        initialize_head=True,
        head_node_args={
            "num_cpus": 2,
            "temp_dir": os.path.join(temp, "ray"),
            "include_dashboard": False,
        },
    )
    try:
        cluster.add_node(num_cpus=2)
        cluster.wait_for_nodes()
        ray.init(
            address=cluster.address,
            namespace=NAMESPACE,
            logging_level="WARNING",
            log_to_driver=False,
        )
        yield cluster
    finally:
        gc.collect()  # actor handles of stopped front-ends let go while Ray is still up
        ray.shutdown()
        cluster.shutdown()
        if saved is None:
            os.environ.pop("RAY_TMPDIR", None)
        else:
            os.environ["RAY_TMPDIR"] = saved
        shutil.rmtree(temp, ignore_errors=True)


@pytest.fixture(scope="module", autouse=True)
def patient_starts():
    """An actor's start (a Ray worker process importing the session's stack, then its mapper)
    takes well over the server's 60 s when both cores are busy with other work (measured: the
    first create then gets server_full); these tests are about what happens once it runs.
    Below the test client's CREATE_TIMEOUT_S, so that a refusal still reaches it."""
    from server.sessions.processes import ray_workers

    with pytest.MonkeyPatch.context() as m:
        m.setattr(ray_workers, "START_TIMEOUT_S", CREATE_TIMEOUT_S - 15.0)
        yield


@pytest.fixture(scope="module")
def room(shared_data):
    return open_dataset(shared_data / "synthetic_room0")


def _actor_alive(sid: str) -> bool:
    try:
        ray.get_actor(f"session-{sid}", namespace=NAMESPACE)
        return True
    except ValueError:
        return False


def _descendants(pid: int) -> set[int]:
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(entry.name))
    found, todo = set(), [pid]
    while todo:
        for child in children.get(todo.pop(), []):
            if child not in found:
                found.add(child)
                todo.append(child)
    return found


def _stat(pid: int) -> list[str]:
    """The fields of /proc/<pid>/stat after the command name (state, ppid, ...)."""
    return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()


def _cpu_ticks(pid: int) -> int:
    fields = _stat(pid)
    return int(fields[11]) + int(fields[12])  # utime + stime


def _ray_addresses() -> set[str]:
    """The local and remote IPv4/IPv6 addresses of every TCP socket of this process's children
    (Ray's GCS, raylets, workers), from /proc."""
    inodes = set()
    for pid in _descendants(os.getpid()):
        try:
            for fd in Path(f"/proc/{pid}/fd").iterdir():
                try:
                    target = os.readlink(fd)
                except OSError:
                    continue
                if target.startswith("socket:["):
                    inodes.add(target[8:-1])
        except OSError:
            continue
    addresses = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        for line in Path(table).read_text().splitlines()[1:]:
            cols = line.split()
            if cols[9] in inodes:
                addresses |= {_ip(cols[1]), _ip(cols[2])}
    return addresses


def _ip(hex_address: str) -> str:
    raw = bytes.fromhex(hex_address.split(":")[0])
    if len(raw) == 4:
        return ".".join(str(b) for b in raw[::-1])
    words = [raw[i : i + 4][::-1] for i in range(0, 16, 4)]
    raw = b"".join(words)
    if raw[:12] == b"\0" * 10 + b"\xff\xff":
        return ".".join(str(b) for b in raw[12:])
    return raw.hex()


def _loopback(address: str) -> bool:
    return (
        address.startswith("127.") or address == "0.0.0.0" or address in ("0" * 31 + "1", "0" * 32)
    )


def test_sessions_on_a_two_node_cluster(cluster, room, tmp_path):
    t0 = time.monotonic()
    data = tmp_path / "data"
    node_ids = {n["NodeID"] for n in ray.nodes() if n["Alive"]}
    assert len(node_ids) == 2
    front1 = LiveServer(data, ray=cluster.address)
    servers = [front1]
    try:
        # Each create starts an actor, a process on its node (seconds on a busy machine).
        (s1, t1), (s2, t2) = create_session(front1.url), create_session(front1.url)
        workers = [session_status(front1.url, s, t)["worker"] for s, t in ((s1, t1), (s2, t2))]
        assert all(w["kind"] == "ray" for w in workers), workers
        assert {w["node_id"] for w in workers} == node_ids, workers  # one session on each node
        assert all(w["node_ip"].startswith("127.") for w in workers), workers

        async def first_poses():
            a = await Stream(front1.ws_url, s1, t1, room).open()
            b = await Stream(front1.ws_url, s2, t2, room).open()
            await asyncio.gather(a.send_range(range(6)), b.send_range(range(6)))
            return a, b

        a1, b1 = asyncio.run(first_poses())
        # Both sessions track the room: poses move along, none lost.
        for stream in (a1, b1):
            assert all(p["state"] != "lost" for p in stream.poses), stream.poses
            motion = np.linalg.norm(
                P.pose_matrix(stream.poses[-1])[:3, 3] - P.pose_matrix(stream.poses[0])[:3, 3]
            )
            assert motion < 1.0

        # A second front-end on the same cluster authorizes s1 with its token and takes its
        # socket over: the first front-end's socket is told, and the poses go to the new one.
        front2 = LiveServer(data, ray=cluster.address)
        servers.append(front2)
        assert session_status(front2.url, s1, t1)["worker"]["node_id"] == workers[0]["node_id"]
        assert (
            httpx.get(f"{front2.url}/api/sessions/{s1}", headers=auth("wrong")).status_code == 404
        )

        async def take_over():
            await a1.open()  # the phone, still on front1: a new socket, a hello
            await a1.send_range(range(2), first_index=6)  # a new socket numbers from 0
            a2 = await Stream(front2.ws_url, s1, t1, room).open()
            ended = await a1.answer()  # front1's socket: taken over
            assert ended["type"] == "error" and ended["name"] == "session_taken_over", ended
            await a2.send_range(range(4), first_index=8)
            await a1.close()
            return a2

        a2 = asyncio.run(take_over())
        assert len(a2.poses) == 4

        # The first front-end stops (a restart): the sessions live on, a new front-end finds
        # them and they stream on.
        front1.stop()
        servers.remove(front1)
        assert _actor_alive(s1) and _actor_alive(s2)
        # Its threads ended with it, those of the sessions it let go of too (a poll still inside
        # ray.get after ray.shutdown would end this whole process): only front2 polls, for s1.
        polls = sorted(t.name for t in threading.enumerate() if t.name.startswith("ray-poll-"))
        assert polls == [f"ray-poll-{s1}"], polls
        front3 = LiveServer(data, ray=cluster.address)
        servers.append(front3)
        status = session_status(front3.url, s2, t2)
        assert status["closed"] is False and status["worker"]["kind"] == "ray", status
        assert status["frames_processed"] >= 6

        async def stream_on():
            b3 = await Stream(front3.ws_url, s2, t2, room).open()
            await b3.send_range(range(4), first_index=6)
            a3 = await Stream(front3.ws_url, s1, t1, room).open()
            await a3.send_range(range(3), first_index=12)
            await asyncio.gather(b3.close(), a3.close())
            return a3, b3

        a3, b3 = asyncio.run(stream_on())
        assert len(a3.poses) == 3 and len(b3.poses) == 4
        status = session_status(front3.url, s1, t1)
        assert status["frames_processed"] >= 6 + 2 + 4 + 3 - 2, status
        assert status["out_of_order_calls"] == 0 and status["foreign_frames"] == 0, status
        # Frames came by the front-ends' streams, not by Ray calls.
        assert 3 <= status["streamed_frames"] <= status["frames_received"], status

        # Every Ray socket stayed on the loopback.
        addresses = _ray_addresses()
        assert addresses, "found no socket of Ray's processes to check"
        outside = {a for a in addresses if not _loopback(a)}
        assert not outside, f"Ray sockets outside 127.0.0.0/8: {outside}"

        # Deleting a session ends its actor; closing one saves it and ends its actor.
        assert httpx.delete(f"{front3.url}/api/sessions/{s2}", headers=auth(t2)).status_code in (
            200,
            204,
        )
        deadline = time.monotonic() + 10
        while _actor_alive(s2) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert not _actor_alive(s2)
        assert not (data / "sessions" / s2).exists()
    finally:
        for server in servers:
            server.stop()  # detached actors left over end with the cluster
    print(f"ray test body: {time.monotonic() - t0:.1f} s")


@pytest.mark.parametrize("killed", ["mapper", "worker"])
def test_a_session_runs_in_its_actors_processes_whose_death_fails_it(
    cluster, room, tmp_path, killed
):
    """The actor runs the session in processes of its own, its children (so on its node): a
    worker that tracks (its CPU time grows with the frames) and a mapper at a lower priority
    that fuses (its CPU time and the map grow). SIGKILL either: as under the process workers,
    the session fails (the mapper's death at the next fusion, the worker's at once), its client
    hears session_failed and the close 4010; the session is closed and saved with the failure,
    and its actor and processes end."""
    data = tmp_path / "data"
    front = LiveServer(data, ray=cluster.address)
    try:
        sid, token = create_session(front.url)
        worker = session_status(front.url, sid, token)["worker"]
        actor, tracker, mapper = worker["actor_pid"], worker["pid"], worker["mapper_pid"]
        assert worker["kind"] == "ray" and len({actor, tracker, mapper} - {None}) == 3, worker
        # The actor's children: on its node, ending with it.
        assert int(_stat(mapper)[1]) == actor and int(_stat(tracker)[1]) == actor
        assert os.getpriority(os.PRIO_PROCESS, mapper) > os.getpriority(os.PRIO_PROCESS, tracker)
        victim = {"mapper": mapper, "worker": tracker}[killed]
        why = {"mapper": "mapping process died", "worker": "worker process died"}[killed]
        stream = Stream(front.ws_url, sid, token, room)
        cpu0, tracker_cpu0 = _cpu_ticks(mapper), _cpu_ticks(tracker)

        async def stream_then_kill():
            await stream.open()
            await stream.send_range(range(12))
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline:
                status = session_status(front.url, sid, token)
                if status["map"].get("frames_integrated", 0) > 0:
                    break
                await asyncio.sleep(0.2)
            fused_cpu = _cpu_ticks(mapper) - cpu0
            tracked_cpu = _cpu_ticks(tracker) - tracker_cpu0
            os.kill(victim, signal.SIGKILL)
            answers = []
            for seq in range(12, 72):  # until a fusion finds the mapper gone
                f = room[seq % len(room)]
                await stream.conn.send_frame(P.make_frame(seq, f.timestamp, f.colour, f.depth))
                answers.append(await stream.answer())
                if answers[-1]["type"] == "error":
                    break
            with pytest.raises(websockets.ConnectionClosed) as closed:
                while True:
                    await stream.answer()
            return status, (fused_cpu, tracked_cpu), answers[-1], closed.value.rcvd.code

        status, (fused_cpu, tracked_cpu), error, close_code = asyncio.run(stream_then_kill())
        assert status["map"]["frames_integrated"] > 0, status["map"]
        # The fusing took the mapper's CPU, the tracking the worker's, not the actor's.
        assert fused_cpu > 0 and tracked_cpu > 0
        assert error["type"] == "error" and error["name"] == "session_failed", error
        assert why in error["message"], error
        assert close_code == P.CLOSE_CODES["session_failed"]
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and (
            _actor_alive(sid) or process_running(mapper) or process_running(tracker)
        ):
            time.sleep(0.2)
        assert not _actor_alive(sid)
        assert not process_running(mapper) and not process_running(tracker)
        status = session_status(front.url, sid, token)
        assert status["closed"] is True and why in status["failure"], status
        meta = (data / "sessions" / sid / "meta.json").read_text()
        assert why in meta
    finally:
        front.stop()


def _end_leftover_sessions() -> None:
    """End the session actors the earlier tests left (a front-end that stops lets go of its
    sessions), and wait until every CPU of the cluster is free again."""
    for entry in ray.util.list_named_actors(all_namespaces=True):
        if entry["namespace"] == NAMESPACE and entry["name"].startswith("session-"):
            try:
                ray.kill(ray.get_actor(entry["name"], namespace=NAMESPACE), no_restart=True)
            except ValueError:
                continue
    deadline = time.monotonic() + 30
    while ray.available_resources().get("CPU", 0) < ray.cluster_resources()["CPU"]:
        assert time.monotonic() < deadline, ray.available_resources()
        time.sleep(0.2)


def _open_room(front, ds, frames: int) -> tuple[str, str, str, str, str]:
    """An owner session that streamed ``frames`` frames of ``ds`` and stays live, and a phone
    joined into its room: (owner id, its token, the phone's id, its token, the join token)."""
    sessions = f"{front.url}/api/sessions"
    a, token_a = create_session(front.url)
    _stream(front, a, token_a, ds, 0, frames)
    wait_for_status(front.url, a, token_a, map_caught_up, "the owner's map")
    join_token = httpx.post(f"{sessions}/{a}/invites", headers=auth(token_a)).json()["join_token"]
    r = httpx.post(sessions, json={"join": a}, headers=auth(join_token), timeout=CREATE_TIMEOUT_S)
    assert r.status_code == 201, r.text
    return a, token_a, r.json()["id"], r.json()["token"], join_token


def _gone(map_pid: int, actor_sid: str) -> bool:
    """The room's map process is gone (reaped: not even a zombie) and so is the owner's actor,
    within 30 s."""
    deadline = time.monotonic() + 30
    while Path(f"/proc/{map_pid}").exists() or _actor_alive(actor_sid):
        if time.monotonic() > deadline:
            return False
        time.sleep(0.2)
    return True


def test_a_shared_room_runs_on_its_owners_node_with_one_map(
    cluster, shared_data, tmp_path, monkeypatch
):
    """A phone joins a live room under Ray: its actor is placed on the owner's node (the room's
    map listens there, on an abstract Unix socket), starts no mapper and fuses into the owner's
    map (both sessions report that map, grown by the phone's frames). With the node's CPUs
    taken, another phone is refused with room_full (the room's node, not the cluster). The
    owner's end (closed and saved; in a second room, deleted) leaves the map serving the phone
    on, the owner's actor lingering for it; after the phone's end the map's process is gone
    (reaped by that actor: no orphan) and so is the actor."""
    from server.sessions.processes import ray_workers

    _end_leftover_sessions()
    ds = open_dataset(shared_data / "7scenes_a")
    front = LiveServer(tmp_path / "data", ray=cluster.address)
    sessions = f"{front.url}/api/sessions"
    try:
        a, token_a, b, token_b, join_token = _open_room(front, ds, 40)
        owner = session_status(front.url, a, token_a)["map"]
        worker_a = session_status(front.url, a, token_a)["worker"]
        worker_b = session_status(front.url, b, token_b)["worker"]
        assert worker_a["node_id"] == worker_b["node_id"], (worker_a, worker_b)
        map_pid = worker_a["mapper_pid"]
        assert worker_b["mapper_pid"] is None and process_running(map_pid)

        # Placed in the owner's room, and its frames fuse into the owner's map: one map.
        s_b = _stream(front, b, token_b, ds, 60, 20)
        states = [p["state"] for p in s_b.poses]
        first_ok = next(k for k, st in enumerate(states) if st != "lost")
        assert first_ok <= 5 and states.count("lost") == first_ok, states
        joined = wait_for_status(front.url, b, token_b, map_caught_up, "the phone's fusion")
        shared = session_status(front.url, a, token_a)["map"]
        assert shared["frames_integrated"] == joined["map"]["frames_integrated"]
        assert shared["frames_integrated"] > owner["frames_integrated"], (shared, owner)

        # The owner's node (2 CPUs) is full: a third phone has nowhere to run.
        monkeypatch.setattr(ray_workers, "START_TIMEOUT_S", 3.0)
        r = httpx.post(sessions, json={"join": a}, headers=auth(join_token), timeout=60)
        assert r.status_code == 409 and r.json()["error"]["code"] == "room_full", r.text
        assert "node" in r.json()["error"]["message"], r.text
        monkeypatch.undo()

        # The owner's session closes (as the reaper closes it: saved): the room's map serves
        # the phone on, its actor lingering for it.
        assert front.app.state.manager.close(a)
        assert session_status(front.url, a, token_a)["closed"] is True
        before = session_status(front.url, b, token_b)["map"]["frames_integrated"]
        s_later = _stream(front, b, token_b, ds, 80, 9)
        assert all(p["state"] != "lost" for p in s_later.poses), s_later.poses
        later = wait_for_status(front.url, b, token_b, map_caught_up, "the map, owner gone")
        assert later["map"]["frames_integrated"] > before, later["map"]
        assert process_running(map_pid) and _actor_alive(a)

        # The phone leaves: the map's process ends, reaped by the owner's actor, which ends.
        assert httpx.delete(f"{sessions}/{b}", headers=auth(token_b)).status_code == 204
        assert _gone(map_pid, a), "the room's map or its owner's actor outlived its phones"
        assert not _actor_alive(b)

        # A deleted owner (ended at once, unsaved) leaves its room's map serving too.
        a, token_a, b, token_b, _ = _open_room(front, ds, 12)
        map_pid = session_status(front.url, a, token_a)["worker"]["mapper_pid"]
        assert httpx.delete(f"{sessions}/{a}", headers=auth(token_a)).status_code == 204
        s_b = _stream(front, b, token_b, ds, 4, 6)
        assert any(p["state"] != "lost" for p in s_b.poses), s_b.poses
        assert (
            wait_for_status(front.url, b, token_b, map_caught_up, "the map")["map"][
                "frames_integrated"
            ]
            > 0
        )
        assert process_running(map_pid) and _actor_alive(a)
        assert httpx.delete(f"{sessions}/{b}", headers=auth(token_b)).status_code == 204
        assert _gone(map_pid, a), "the room's map or its owner's actor outlived its phones"
    finally:
        front.stop()


def test_a_local_ray_runs_the_sessions_at_the_servers_priority(monkeypatch):
    """``serve --ray local`` starts Ray with worker_niceness 0: Ray's default, 15, put a
    session's tracking below the front-end and anything else on the machine. Joining a cluster
    leaves its nodes' own setting."""
    from ray._private import ray_constants

    from server.sessions.processes import ray_workers

    calls = []
    monkeypatch.setattr(ray_workers.ray, "is_initialized", lambda: False)
    monkeypatch.setattr(ray_workers.ray, "init", lambda **kwargs: calls.append(kwargs))
    monkeypatch.setattr(ray_constants, "ENABLE_RAY_CLUSTER", ray_constants.ENABLE_RAY_CLUSTER)
    monkeypatch.setattr(ray_workers, "_RAY_USERS", 0)
    monkeypatch.setattr(ray_workers, "_RAY_OURS", False)
    assert ray_workers._connect("local") is True
    assert ray_workers._connect("ray://head:10001") is False
    local, cluster = calls
    assert local["_system_config"] == {"worker_niceness": 0}
    assert local["address"] == "local" and local["include_dashboard"] is False
    assert cluster["_system_config"] is None
