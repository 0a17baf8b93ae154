"""Loop closure: each new keyframe is looked up among the keyframes made long enough before it,
a verified match becomes an edge of a pose graph over keyframes, and the graph is optimised
(Open3D's ``PoseGraph`` and ``global_optimization``, Levenberg-Marquardt, line processes).

Edges: odometry between consecutive keyframes (as the tracker chained them) and verified loops,
each refined point-to-plane on the two keyframes' depth and weighted by Open3D's information
matrix of that alignment. Nodes are T_world_keyframe (4x4, metres); the first stays fixed.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d

from server.geometry import Intrinsics, backproject, invert
from server.geometry.arrays import Float32Array, FloatArray
from server.registration.config import RegistrationConfig
from server.registration.place import KeyframeDatabase, PlaceFeatures
from server.registration.verify import find_place

log = logging.getLogger(__name__)

_reg = o3d.pipelines.registration


@dataclass
class LoopEdge:
    """A verified loop: T_old_new maps the new keyframe's camera points into the old one's."""

    old: int
    new: int
    T_old_new: FloatArray
    inliers: int


@dataclass
class _Node:
    kf_id: int
    T_world_keyframe: FloatArray  # as tracked (odometry)
    cloud: o3d.geometry.PointCloud  # depth points in the keyframe's camera frame, with normals


@dataclass
class LoopCloser:
    """Keyframes in, loops found, corrected keyframe poses out (:meth:`optimise`)."""

    K: Intrinsics
    cfg: RegistrationConfig
    database: KeyframeDatabase = field(default_factory=KeyframeDatabase)
    nodes: list[_Node] = field(default_factory=list)
    loops: list[LoopEdge] = field(default_factory=list)

    def add_keyframe(
        self,
        kf_id: int,
        T_world_keyframe: FloatArray,
        features: PlaceFeatures,
        depth: Float32Array,
    ) -> LoopEdge | None:
        """Add a keyframe (ids increasing; depth (H, W) metres, cleaned) and look for a loop
        to keyframes at least ``loops.min_separation`` keyframes older; returns the loop found
        (already an edge of the graph) or None."""
        c = self.cfg.loops
        self.nodes.append(_Node(kf_id, T_world_keyframe.copy(), self._cloud(depth)))
        older = {n.kf_id for n in self.nodes[: max(0, len(self.nodes) - 1 - c.min_separation)]}
        found = None
        if older:
            match = find_place(
                self.database,
                features,
                self.K,
                self.cfg.place,
                self.cfg.solver,
                self.cfg.depth,
                allowed=older,
            )
            if match is not None:
                T = self._refine(match.keyframe_id, kf_id, match.T_keyframe_query)
                if T is not None:
                    found = LoopEdge(match.keyframe_id, kf_id, T, match.inliers)
                    self.loops.append(found)
                    log.info("loop: keyframe %d sees keyframe %d", kf_id, match.keyframe_id)
        self.database.add(kf_id, T_world_keyframe, features)
        return found

    def optimise(self) -> dict[int, FloatArray]:
        """Corrected T_world_keyframe per keyframe id (the odometry's when there is no loop)."""
        if not self.loops:
            return {n.kf_id: n.T_world_keyframe.copy() for n in self.nodes}
        index = {n.kf_id: i for i, n in enumerate(self.nodes)}
        graph = _reg.PoseGraph()
        for n in self.nodes:
            graph.nodes.append(_reg.PoseGraphNode(n.T_world_keyframe))
        dist = self.cfg.loops.icp_distance_m
        for a, b in zip(self.nodes, self.nodes[1:], strict=False):
            T_a_b = invert(a.T_world_keyframe) @ b.T_world_keyframe
            info = _reg.get_information_matrix_from_point_clouds(b.cloud, a.cloud, dist, T_a_b)
            graph.edges.append(
                _reg.PoseGraphEdge(index[b.kf_id], index[a.kf_id], T_a_b, info, uncertain=False)
            )
        for loop in self.loops:
            old, new = self.nodes[index[loop.old]], self.nodes[index[loop.new]]
            info = _reg.get_information_matrix_from_point_clouds(
                new.cloud, old.cloud, dist, loop.T_old_new
            )
            graph.edges.append(
                _reg.PoseGraphEdge(
                    index[loop.new], index[loop.old], loop.T_old_new, info, uncertain=True
                )
            )
        option = _reg.GlobalOptimizationOption(
            max_correspondence_distance=dist,
            edge_prune_threshold=0.25,
            preference_loop_closure=self.cfg.loops.preference,
            reference_node=0,
        )
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            _reg.global_optimization(
                graph,
                _reg.GlobalOptimizationLevenbergMarquardt(),
                _reg.GlobalOptimizationConvergenceCriteria(),
                option,
            )
        return {n.kf_id: np.asarray(graph.nodes[index[n.kf_id]].pose).copy() for n in self.nodes}

    # ---- helpers ---------------------------------------------------------------------------
    def _cloud(self, depth: Float32Array) -> o3d.geometry.PointCloud:
        points, _ = backproject(depth, self.K, stride=self.cfg.loops.cloud_stride)
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=0.05, max_nn=20))
        cloud.orient_normals_towards_camera_location(np.zeros(3))
        return cloud

    def _refine(self, old_id: int, new_id: int, T_old_new: FloatArray) -> FloatArray | None:
        """Point-to-plane ICP of the new keyframe's depth onto the old one's from the verified
        guess; None when too little of it fits (a guess that ICP cannot confirm)."""
        old = next(n for n in self.nodes if n.kf_id == old_id)
        new = next(n for n in self.nodes if n.kf_id == new_id)
        c = self.cfg.loops
        result = _reg.registration_icp(
            new.cloud,
            old.cloud,
            c.icp_distance_m,
            T_old_new,
            _reg.TransformationEstimationPointToPlane(),
            _reg.ICPConvergenceCriteria(max_iteration=30),
        )
        if result.fitness < c.min_icp_fitness:
            log.info("loop %d-%d refused: ICP fitness %.2f", old_id, new_id, result.fitness)
            return None
        refined: FloatArray = np.array(result.transformation, dtype=np.float64)
        return refined
