"""The paper's RGB-D registration: FAST + pyramidal LK correspondences, Gauss-Newton on SE(3),
dense point-to-plane refinement, keyframes."""

from server.registration.results import TrackingState, TrackResult
from server.registration.tracker import Tracker

__all__ = ["Tracker", "TrackingState", "TrackResult"]
