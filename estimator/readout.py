"""What the estimator reports, read out of its graph: each camera's state and pose, the markers'
poses with covariances (a few recomputed per call), object markers through the camera that sees
them best, and anchors whose observations disagree with their survey. A part of ``Estimator``
(``estimator.graph``), apart because reading the answer is its own concern and its own cost.
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import gtsam
import numpy as np

from estimator.estimate import BestView, CameraEstimate, CameraState, Estimate, PoseEstimate, through_camera
from estimator.init import CameraKey
from estimator.keyframes import moving_frame, place_frame
from estimator.pairs import Pair
from estimator.resect import resect
from estimator.symbols import marker_symbol
from schemas.geometry import cov_gtsam_to_ros, invert_pose

if TYPE_CHECKING:
    from estimator.graph import CameraTrack

#: Covariances recomputed per ``estimate`` beyond new variables' (the rest are the cached ones): in
#: a 64-camera ring one costs 0.1-3 ms after an update (iSAM2 recomputes the Bayes tree's shortcuts
#: to the root), all 1,064 up to 300 ms, and a settled variable's covariance barely changes.
COVARIANCES_PER_ESTIMATE = 8
#: How often the anchors are checked against their observations (ns): ~15 ms at 64 cameras.
ANCHOR_CHECK_NS = 1_000_000_000


class Readout:
    """``Estimator.estimate`` and what it needs; mixed into ``Estimator``, whose state it reads."""

    def estimate(self, now_ns: int, with_covariance: bool = True) -> Estimate:
        """Current poses and states. ``now_ns`` decides staleness (same clock as the stamps)."""
        stale_ns = int(self.config.stale_after_s * 1e9)
        cams: dict[str, CameraEstimate] = {}
        posed: dict[str, int] = {}  # camera id -> its variable, for those posed by the graph
        for cid, track in self.tracks.items():
            key = self._camera_key((cid, track.segment)) if (cid, track.segment) in self.camera_index else None
            pose = None
            if track.moving or track.suspect > 0:  # suspect frames are held back: report it at once
                state = CameraState.MOVING
                T = self._track_pose(track)
                pose = None if T is None else PoseEstimate(T, None)
            elif (cid, track.segment) in self._held:
                state = CameraState.LOCALIZED
                pose = PoseEstimate(*self._resect(self._mapped_pairs((cid, track.segment))))
                self._resected[(cid, track.segment)] = pose.T
            elif key is not None and key in self.in_graph:
                state = CameraState.LOCALIZED
                pose = PoseEstimate(self._pose(key), None)  # its covariance below, with the markers'
                posed[cid] = key
            else:
                state = CameraState.UNANCHORED
            if now_ns - track.last_stamp_ns > stale_ns:
                state = CameraState.STALE
            cams[cid] = CameraEstimate(cid, state, track.segment, track.last_stamp_ns, track.markers_seen, pose)
        marker_keys = [key for key in sorted(self.in_graph) if gtsam.Symbol(key).chr() == ord("m")]
        if with_covariance:
            covs = self._covariances(list(posed.values()) + marker_keys)
            for cid, key in posed.items():
                cams[cid] = replace(cams[cid], pose=PoseEstimate(cams[cid].pose.T, covs[key]))
        else:
            covs = {}
        markers = {gtsam.Symbol(key).index(): PoseEstimate(self._pose(key), covs.get(key)) for key in marker_keys}
        if now_ns - self._flagged[0] >= ANCHOR_CHECK_NS or now_ns < self._flagged[0]:
            self._flagged = (now_ns, self._flagged_anchors())
        return Estimate(cams, markers, self._object_markers(cams), self._flagged[1])

    def _covariances(self, keys: list[int]) -> dict[int, np.ndarray]:
        """Covariances (6x6, ROS order) of the variables ``keys``: new ones computed now, and the next
        COVARIANCES_PER_ESTIMATE of the rest in turn; the others as last computed (at most
        len(keys) / COVARIANCES_PER_ESTIMATE estimates old: a camera that moved is a new variable)."""
        cache = self._cov
        for key in [k for k in cache if k not in self.in_graph]:
            del cache[key]
        due = [k for k in keys if k not in cache]
        if len(keys) > len(due):
            start = self._cov_next % len(keys)
            turn = (keys[start:] + keys[:start])[:COVARIANCES_PER_ESTIMATE]
            self._cov_next = start + len(turn)
            due += [k for k in turn if k in cache]
        for key in due:
            cache[key] = self._covariance(key)
        return {k: cache[k] for k in keys}

    def _track_pose(self, track: CameraTrack) -> np.ndarray | None:
        """Pose of a moving camera from its newest frame against the mapped markers (not in the
        graph), placed as a moving frame is (``place_frame``: full marker poses, not a fit of their
        centres, which markers along a line or a shallow arc, a ring's seen from inside, leave free
        to turn about it, metres off at the camera); one marker, or none agreeing: all of them."""
        mapped = [o for k, o in track.latest.items() if marker_symbol(k) in self.in_graph]
        frame = moving_frame(track.camera_id, track.last_stamp_ns, mapped, 0)
        if not len(frame.ids):
            return None
        world = self._mapped(frame.ids)
        placed = place_frame(frame, world, self.rotation_floor_rad)
        if placed is not None:
            return placed.world_T_camera
        return resect(
            np.stack(list(world.values())),
            np.zeros_like(frame.covariances),
            frame.poses,
            frame.covariances,
            self.config.huber_k,
        )[0]

    def _mapped(self, ids: np.ndarray) -> dict[int, np.ndarray]:
        """world_T_marker of those of ``ids`` in the graph."""
        return {int(mk): self._pose(marker_symbol(int(mk))) for mk in ids if marker_symbol(int(mk)) in self.in_graph}

    def _object_markers(self, cams: dict[str, CameraEstimate]) -> dict[int, PoseEstimate]:
        """Newest pose of each object marker, through the camera that sees it best."""
        best: BestView[int, PoseEstimate] = BestView()
        for cid, track in self.tracks.items():
            cam = cams.get(cid)
            if cam is None or cam.state is not CameraState.LOCALIZED or cam.pose is None:
                continue
            for mk, obs in track.latest.items():
                if mk not in self.object_markers:
                    continue
                cam_cov = cam.pose.covariance if cam.pose.covariance is not None else np.zeros((6, 6))
                T, cov = through_camera(cam.pose.T, cam_cov, obs.camera_T_marker, obs.covariance)
                best.offer(mk, cov, PoseEstimate(T, cov))
        return {mk: best.pop(mk) for mk in best.keys()}

    def _flagged_anchors(self) -> list[int]:
        """Anchors whose observations disagree with their surveyed pose (moved since the survey).

        Per camera, every reference it sees (an anchor's surveyed pose, a mapped marker's
        estimate) implies a camera pose through its observation: reference @ inv(camera_T_marker).
        The largest group of references that agree (within ``anchor_check_m``) is the consensus;
        an anchor outside it is flagged. Full poses, not marker centres: markers on one line would
        leave a point fit free to rotate about it and blame the wrong anchor.
        """
        flagged: set[int] = set()
        by_cam: dict[CameraKey, dict[int, Pair]] = {}
        for (cam, mk), pair in self.pairs.items():
            if pair.n > 0 and mk not in self.object_markers:
                by_cam.setdefault(cam, {})[mk] = pair
        tol = self.config.anchor_check_m
        for seen in by_cam.values():
            if not any(mk in self.anchors for mk in seen):
                continue
            ids, implied = [], []
            for mk, pair in seen.items():
                ref = self.anchors.get(mk)
                if ref is None and marker_symbol(mk) in self.in_graph:
                    ref = self._pose(marker_symbol(mk))
                if ref is not None:
                    ids.append(mk)
                    implied.append((ref @ invert_pose(pair.mean()))[:3, 3])
            if len(ids) < 3:
                continue
            P = np.array(implied)  # (k, 3) camera positions, one per reference; all pairs at once
            agree = np.linalg.norm(P[:, None, :] - P[None, :, :], axis=2) <= tol
            consensus = agree[int(np.argmax(agree.sum(axis=1)))]  # the first largest group, as before
            if consensus.sum() * 2 <= len(ids):
                continue  # no majority: cannot tell which anchor moved
            flagged |= {mk for mk, ok in zip(ids, consensus) if mk in self.anchors and not ok}
        return sorted(flagged)

    def _pose(self, key: int) -> np.ndarray:
        return self.values.atPose3(key).matrix()

    def _covariance(self, key: int) -> np.ndarray:
        return cov_gtsam_to_ros(self.isam.marginalCovariance(key))
