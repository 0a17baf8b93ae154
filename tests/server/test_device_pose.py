"""The phone's own pose on the wire (frame.T_device_camera): the server's tracker starts from
its motion and comes back after frames go missing, and the poses it answers stay in the map."""

from __future__ import annotations

import asyncio

import numpy as np

from server import protocol as P
from server.datasets import open_dataset
from server.geometry import exp_se3
from server.registration.config import RegistrationConfig
from tests.conftest import Stream

BURST = 15  # frames lost in a row, after every 3 * BURST that arrive


def arriving(n: int) -> list[int]:
    return [i for i in range(n) if i % (4 * BURST) < 3 * BURST]


def stream(server, dataset, with_prior: bool) -> list[dict]:
    """The sequence with bursts of frames missing, with or without the device's pose, which
    lives in a world of its own (a rigid transform away from the map's)."""
    T_device_world = exp_se3(np.array([0.3, -0.2, 0.1, 0.4, 1.5, -0.7]))
    gt = dataset.ground_truth
    sid, token = server.create_session()
    s = Stream(server.ws_url, sid, token, dataset)

    async def go():
        await s.open()
        for seq, i in enumerate(arriving(len(dataset))):
            prior = T_device_world @ gt.poses[i] if with_prior else None
            await s.send(seq, index=i, T_device_camera=prior)
        await s.close()

    asyncio.run(go())
    return s.poses


def relative_errors(poses: list[dict], dataset) -> np.ndarray:
    """Translation error (m) of each pose relative to the first, against the ground truth's."""
    idx = arriving(len(dataset))
    est = np.array([P.pose_matrix(p) for p in poses])
    gt = dataset.ground_truth.poses[idx]
    rel_est = np.linalg.inv(est[0]) @ est
    rel_gt = np.linalg.inv(gt[0]) @ gt
    return np.linalg.norm(rel_est[:, :3, 3] - rel_gt[:, :3, 3], axis=1)


def test_the_device_pose_carries_tracking_over_missing_frames(live_server, shared_data):
    dataset = open_dataset(shared_data / "synthetic_room0")
    server = live_server()
    # Flow alone (place recognition's recovery off) loses track over the bursts.
    flow_only = RegistrationConfig().with_overrides(relocalise={"enabled": False})
    without = stream(live_server(registration=flow_only), dataset, with_prior=False)
    with_prior = stream(server, dataset, with_prior=True)
    lost_without = sum(p["state"] == "lost" for p in without)
    lost_with = sum(p["state"] == "lost" for p in with_prior)
    assert lost_without > 0, "the bursts no longer lose tracking: the test shows nothing"
    assert lost_with == 0, f"{lost_with} frames lost with the device's pose"
    # Poses are in the map (the session's first camera), not in the device's world.
    assert np.allclose(P.pose_matrix(with_prior[0]), np.eye(4), atol=1e-6)
    assert relative_errors(with_prior, dataset).max() < 0.03
