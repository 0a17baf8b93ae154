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

from server.geometry import Intrinsics, backproject, invert, orthonormalize
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
    T_world_keyframe: FloatArray  # as tracked (odometry), in the world it was tracked in
    cloud: o3d.geometry.PointCloud  # depth points in the keyframe's camera frame
    # Normals are estimated the first time the keyframe is a loop's ICP target (about half of
    # a keyframe's cost when done for every one; most never are a target).
    normals: bool = False
    # Where the graph puts it now: chained from the previous node's estimate by the odometry edge
    # until an optimisation corrects it (the initial value of the next optimisation).
    estimate: FloatArray = field(default_factory=lambda: np.eye(4))


@dataclass
class _Edge:
    """A pose-graph edge with its information matrix, computed once when the edge is made (the
    point-to-plane correspondences of two clouds cost milliseconds; an optimisation re-uses
    them)."""

    source: int  # node index (the newer keyframe)
    target: int  # node index (the older keyframe)
    T_target_source: FloatArray
    information: FloatArray
    uncertain: bool


@dataclass
class LoopCloser:
    """Keyframes in, loops found, corrected keyframe poses out (:meth:`optimise`).

    ``refused`` counts the keyframes whose place candidates were all refused (by verification,
    or by the ICP that refines a verified match): loops proposed and not taken."""

    K: Intrinsics
    cfg: RegistrationConfig
    database: KeyframeDatabase = field(default_factory=KeyframeDatabase)
    nodes: list[_Node] = field(default_factory=list)
    loops: list[LoopEdge] = field(default_factory=list)
    refused: int = 0
    _edges: list[_Edge] = field(default_factory=list)
    _index: dict[int, int] = field(default_factory=dict)

    def add_keyframe(
        self,
        kf_id: int,
        T_world_keyframe: FloatArray,
        features: PlaceFeatures,
        depth: Float32Array,
        T_world_previous: FloatArray | None = None,
    ) -> LoopEdge | None:
        """Add a keyframe (ids increasing; T_world_keyframe 4x4 metres; depth (H, W) metres,
        cleaned) and look for a loop to keyframes at least ``loops.min_separation`` keyframes
        older; returns the loop found (already an edge of the graph) or None.

        ``T_world_previous``: the previous keyframe's pose in the same world as this one's (a
        live session's tracker may have been corrected between the two); None: the previous
        node's own, which holds when nothing was corrected (offline)."""
        c = self.cfg.loops
        node = _Node(
            kf_id, T_world_keyframe.copy(), self._cloud(depth), estimate=T_world_keyframe.copy()
        )
        if self.nodes:
            prev = self.nodes[-1]
            T_prev = prev.T_world_keyframe if T_world_previous is None else T_world_previous
            # Projected onto SO(3) before ``invert`` (which takes R^T for the inverse) and after
            # chaining: a live session's T_prev is the previous estimate carried back from the
            # graph, and unprojected, each keyframe doubled its rotation's departure from
            # orthonormality (1e-16 grew to a metre-sized correction within ~90 keyframes).
            T_a_b = invert(orthonormalize(T_prev)) @ T_world_keyframe
            node.estimate = orthonormalize(prev.estimate @ T_a_b)
            info = _reg.get_information_matrix_from_point_clouds(
                node.cloud, prev.cloud, c.icp_distance_m, T_a_b
            )
            self._edges.append(_Edge(len(self.nodes), len(self.nodes) - 1, T_a_b, info, False))
        self._index[kf_id] = len(self.nodes)
        self.nodes.append(node)
        older = {n.kf_id for n in self.nodes[: max(0, len(self.nodes) - 1 - c.min_separation)]}
        found = None
        if older:
            tried: list[int] = []
            match = find_place(
                self.database,
                features,
                self.K,
                self.cfg.place,
                self.cfg.solver,
                self.cfg.depth,
                allowed=older,
                tried=tried,
            )
            T = (
                None
                if match is None
                else self._refine(match.keyframe_id, kf_id, match.T_keyframe_query)
            )
            if match is not None and T is not None:
                found = LoopEdge(match.keyframe_id, kf_id, T, match.inliers)
                self.loops.append(found)
                old = self.nodes[self._index[match.keyframe_id]]
                info = c.loop_information_scale * _reg.get_information_matrix_from_point_clouds(
                    node.cloud, old.cloud, c.icp_distance_m, T
                )
                self._edges.append(
                    _Edge(self._index[kf_id], self._index[match.keyframe_id], T, info, True)
                )
                log.info("loop: keyframe %d sees keyframe %d", kf_id, match.keyframe_id)
            elif tried:
                self.refused += 1
        self.database.add(kf_id, T_world_keyframe, features)
        return found

    def optimise(self) -> dict[int, FloatArray]:
        """Corrected T_world_keyframe per keyframe id (the odometry's when there is no loop),
        in the world of the first keyframe, which stays fixed. Starts from the last estimates,
        with the information matrices cached at each edge's making."""
        if not self.loops:
            return {n.kf_id: n.estimate.copy() for n in self.nodes}
        graph = _reg.PoseGraph()
        for n in self.nodes:
            graph.nodes.append(_reg.PoseGraphNode(n.estimate))
        for e in self._edges:
            graph.edges.append(
                _reg.PoseGraphEdge(
                    e.source, e.target, e.T_target_source, e.information, uncertain=e.uncertain
                )
            )
        option = _reg.GlobalOptimizationOption(
            max_correspondence_distance=self.cfg.loops.icp_distance_m,
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
        for i, n in enumerate(self.nodes):
            n.estimate = orthonormalize(np.asarray(graph.nodes[i].pose, dtype=np.float64))
        return {n.kf_id: n.estimate.copy() for n in self.nodes}

    def edges(self) -> list[tuple[int, int, FloatArray, bool]]:
        """The graph's edges as (older keyframe id, newer keyframe id, T_older_newer 4x4
        metres, whether it is a loop): odometry between consecutive keyframes, and loops."""
        return [
            (
                self.nodes[e.target].kf_id,
                self.nodes[e.source].kf_id,
                e.T_target_source.copy(),
                e.uncertain,
            )
            for e in self._edges
        ]

    # ---- helpers ---------------------------------------------------------------------------
    def _cloud(self, depth: Float32Array) -> o3d.geometry.PointCloud:
        points, _ = backproject(depth, self.K, stride=self.cfg.loops.cloud_stride)
        return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))

    @staticmethod
    def _with_normals(node: _Node) -> o3d.geometry.PointCloud:
        """The node's cloud with normals (point-to-plane ICP onto it needs them)."""
        if not node.normals:
            node.cloud.estimate_normals(
                o3d.geometry.KDTreeSearchParamHybrid(radius=0.05, max_nn=20)
            )
            node.cloud.orient_normals_towards_camera_location(np.zeros(3))
            node.normals = True
        return node.cloud

    def _refine(self, old_id: int, new_id: int, T_old_new: FloatArray) -> FloatArray | None:
        """Point-to-plane ICP of the new keyframe's depth onto the old one's from the verified
        guess; None when too little of it fits (a guess that ICP cannot confirm)."""
        old = self.nodes[self._index[old_id]]
        new = self.nodes[self._index[new_id]]
        c = self.cfg.loops
        result = _reg.registration_icp(
            new.cloud,
            self._with_normals(old),
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
