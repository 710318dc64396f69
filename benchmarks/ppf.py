"""Point-pair-feature voting (Drost et al., "Model globally, match locally", CVPR 2010).

The baseline our recognition is measured against (``benchmarks.recognition``), vectorised with
numpy. Every ordered pair of sampled model points (m_r, m_i) is hashed by its feature
F = (|d|, angle(n_r, d), angle(n_i, d), angle(n_r, n_i)), d = m_i - m_r, quantised, with the angle
alpha_m that turns m_i about the x axis once m_r sits at the origin with its normal along +x. In the
scene, each reference point s_r pairs with the points within the model's diameter; a matching
feature votes for (m_r, alpha = alpha_s - alpha_m), and the peak of each reference's accumulator is
a pose: camera_T_object = inv(T_s) Rx(alpha) T_m. Poses are clustered, votes summed, best first.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from schemas.geometry import rotation_angles, rotation_between

#: Quantisation: distance in this share of the model diameter, angles in this many bins over pi.
DISTANCE_STEP = 0.05
ANGLE_BINS = 30
#: Sampled model points at most (all ordered pairs are hashed: 600 is 360k entries).
MAX_MODEL_POINTS = 600
#: Reference points voting at once: their distances to every scene sample and their accumulators
#: (references x model points x angle bins) are held together.
REFS_AT_ONCE = 256


@dataclass(frozen=True)
class PpfModel:
    """A model's hashed point pairs: ``keys`` sorted (P,), with each pair's reference point index
    into ``points`` (P,) and its angle alpha_m (P,, rad). points, normals (M, 3), object frame, m."""

    points: np.ndarray
    normals: np.ndarray
    keys: np.ndarray
    ref: np.ndarray
    alpha: np.ndarray
    step_m: float
    diameter_m: float


@dataclass(frozen=True)
class PpfPose:
    """A pose hypothesis: camera_T_object (4, 4) and the votes of the cluster it heads."""

    camera_T_object: np.ndarray
    votes: float


def _sample(points: np.ndarray, normals: np.ndarray, step_m: float) -> tuple[np.ndarray, np.ndarray]:
    """One point (and its normal) per occupied voxel of side step_m."""
    cells = np.floor(points / step_m).astype(np.int64)
    _, first = np.unique(cells, axis=0, return_index=True)
    first = np.sort(first)
    return points[first], normals[first]


def _to_x(p: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Transforms (N, 4, 4) taking each point p (N, 3) to the origin and its normal n to +x."""
    T = np.tile(np.eye(4), (len(n), 1, 1))
    T[:, :3, :3] = rotation_between(n, np.array([1.0, 0.0, 0.0]))
    T[:, :3, 3] = -np.einsum("nij,nj->ni", T[:, :3, :3], p)
    return T


def _features(p1: np.ndarray, n1: np.ndarray, p2: np.ndarray, n2: np.ndarray, step_m: float) -> np.ndarray:
    """Quantised feature keys (N,) of the pairs (p1, n1) -> (p2, n2), each (N, 3)."""
    d = p2 - p1
    dist = np.linalg.norm(d, axis=1)
    u = d / np.maximum(dist, 1e-12)[:, None]
    bins = ANGLE_BINS / np.pi

    def angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.arccos(np.clip(np.einsum("ij,ij->i", a, b), -1.0, 1.0))

    f = np.stack([dist / step_m, angle(n1, u) * bins, angle(n2, u) * bins, angle(n1, n2) * bins], axis=1)
    q = np.minimum(f.astype(np.int64), [1 << 20, ANGLE_BINS - 1, ANGLE_BINS - 1, ANGLE_BINS - 1])
    return ((q[:, 0] * ANGLE_BINS + q[:, 1]) * ANGLE_BINS + q[:, 2]) * ANGLE_BINS + q[:, 3]


def _alphas(T_ref: np.ndarray, p_other: np.ndarray) -> np.ndarray:
    """Angle (rad) about +x of each other point once its reference is at the origin along +x.
    T_ref (N, 4, 4) from ``_to_x``, p_other (N, 3)."""
    q = np.einsum("nij,nj->ni", T_ref[:, :3, :3], p_other) + T_ref[:, :3, 3]
    return np.arctan2(q[:, 2], q[:, 1])


def train(points: np.ndarray, normals: np.ndarray, diameter_m: float) -> PpfModel:
    """Hash every ordered pair of the model's sampled points (object frame, m; unit normals)."""
    step = DISTANCE_STEP * diameter_m
    p, n = _sample(points, normals, step)
    while len(p) > MAX_MODEL_POINTS:
        step *= 1.2
        p, n = _sample(points, normals, step)
    i, j = np.nonzero(~np.eye(len(p), dtype=bool))
    keys = _features(p[i], n[i], p[j], n[j], step)
    alpha = _alphas(_to_x(p, n)[i], p[j])
    order = np.argsort(keys, kind="stable")
    return PpfModel(p, n, keys[order], i[order], alpha[order], step, diameter_m)


def match(model: PpfModel, points: np.ndarray, normals: np.ndarray, ref_every: int = 5, top: int = 3) -> list[PpfPose]:
    """Pose hypotheses of the model in a scene (points, unit normals (N, 3), camera frame, m), best first.

    The scene is sampled like the model; every ``ref_every``-th sample is a reference point. The
    references vote in chunks (``REFS_AT_ONCE``), so memory stays bounded on a whole frame."""
    s, sn = _sample(points, normals, model.step_m)
    refs = np.arange(0, len(s), ref_every)
    if len(refs) == 0 or len(model.points) < 2:
        return []
    chunks = [_vote(model, s, sn, refs[i : i + REFS_AT_ONCE]) for i in range(0, len(refs), REFS_AT_ONCE)]
    poses, votes = np.concatenate([c[0] for c in chunks]), np.concatenate([c[1] for c in chunks])
    return _cluster(poses, votes, 0.1 * model.diameter_m, np.radians(2 * 360 / ANGLE_BINS))[:top]


def _vote(model: PpfModel, s: np.ndarray, sn: np.ndarray, refs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each reference point's (indices into the scene samples s, normals sn (S, 3)) best pose
    (R, 4, 4) and its votes (R,)."""
    near = np.linalg.norm(s[refs][:, None, :] - s[None, :, :], axis=2) <= model.diameter_m
    near[np.arange(len(refs)), refs] = False
    r, o = np.nonzero(near)  # r indexes refs, o the scene samples
    keys = _features(s[refs[r]], sn[refs[r]], s[o], sn[o], model.step_m)
    T_s = _to_x(s[refs], sn[refs])
    alpha_s = _alphas(T_s[r], s[o])
    lo, hi = np.searchsorted(model.keys, keys, "left"), np.searchsorted(model.keys, keys, "right")
    hits = hi - lo
    pair = np.repeat(np.arange(len(keys)), hits)
    entry = np.repeat(lo - np.cumsum(hits) + hits, hits) + np.arange(hits.sum())
    alpha = (alpha_s[pair] - model.alpha[entry]) % (2 * np.pi)  # turns the model's point onto the scene's
    a_bin = np.minimum((alpha / (2 * np.pi) * ANGLE_BINS).astype(np.int64), ANGLE_BINS - 1)
    m = len(model.points)
    acc = np.bincount((r[pair] * m + model.ref[entry]) * ANGLE_BINS + a_bin, minlength=len(refs) * m * ANGLE_BINS)
    acc = acc.reshape(len(refs), m * ANGLE_BINS)
    best = acc.argmax(axis=1)
    votes = acc[np.arange(len(refs)), best].astype(float)
    m_ref, a_idx = best // ANGLE_BINS, best % ANGLE_BINS
    T_m = _to_x(model.points[m_ref], model.normals[m_ref])
    angle = (a_idx + 0.5) * 2 * np.pi / ANGLE_BINS
    Rx = np.tile(np.eye(4), (len(refs), 1, 1))
    Rx[:, 1, 1], Rx[:, 1, 2], Rx[:, 2, 1], Rx[:, 2, 2] = np.cos(angle), -np.sin(angle), np.sin(angle), np.cos(angle)
    return np.linalg.inv(T_s) @ Rx @ T_m, votes


def _cluster(poses: np.ndarray, votes: np.ndarray, dist_m: float, angle_rad: float) -> list[PpfPose]:
    """Greedy pose clustering, most votes first: a pose within dist_m and angle_rad of a cluster's
    head joins it and adds its votes."""
    heads: list[int] = []
    total: list[float] = []
    for k in np.argsort(-votes, kind="stable"):
        H = poses[heads]  # (h, 4, 4), compared all at once
        near = (np.linalg.norm(H[:, :3, 3] - poses[k, :3, 3], axis=1) <= dist_m) & (
            rotation_angles(H[:, :3, :3], poses[k, :3, :3]) <= angle_rad
        )
        if near.any():
            total[int(np.argmax(near))] += votes[k]  # the first head it is near, as heads were made
        else:
            heads.append(int(k))
            total.append(float(votes[k]))
    order = np.argsort(-np.array(total), kind="stable")
    return [PpfPose(poses[heads[h]], total[h]) for h in order]
