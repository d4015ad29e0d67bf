"""The gauge of a camera rig: a similarity of the whole world (a small turn, shift and change of scale)
applied to the scene and to every camera alike leaves every picture unchanged, so poses estimated from
pictures alone are defined only up to it. `gauge_part` finds that part of small pose corrections
(`gauge_projector`: the same as one matrix), to be removed by pose refinement (stg_train.rig.pose_refine)
and before pose errors are compared with a known truth (stg_train.rig.capture.pose_errors).

Conventions (formats/stg-v1.md): world_to_camera (4, 4), OpenCV; a correction of camera c is the rigid
D_c = [exp([w_c]x) | t_c] applied in camera coordinates (corrected camera D_c W_c), w_c axis-angle in
radians, t_c in world units. To first order its camera frame turns by a_c = -R_c^T w_c in world
coordinates and its centre moves by dC_c = -R_c^T t_c. A similarity (turn omega, relative scale sigma,
shift tau) about the rig's mean centre m moves them by a_c = omega, dC_c = omega x (C_c - m) +
sigma (C_c - m) + tau.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..rotations import cross_matrix, rotation_vector


class Similarity(NamedTuple):
    """A small similarity of the world, to first order (module docstring): turn omega (3,) axis-angle
    radians and relative scale sigma, both about `about` (3,) world units, then shift tau (3,)."""

    omega: np.ndarray
    sigma: float
    tau: np.ndarray
    about: np.ndarray

    def corrections(self, world_to_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(rotation (K, 3), translation (K, 3)): the corrections D_c, in camera coordinates, that move
        cameras with world_to_camera (K, 4, 4) by this similarity (any cameras, not only those it was
        fitted on)."""
        r = world_to_camera[:, :3, :3]
        d = _centres(world_to_camera) - self.about
        move = np.cross(self.omega, d) + self.sigma * d + self.tau
        # back to camera coordinates: w_c = -R_c a_c, t_c = -R_c dC_c
        return -np.einsum("kij,j->ki", r, self.omega), -np.einsum("kij,kj->ki", r, move)


def _centres(world_to_camera: np.ndarray) -> np.ndarray:
    """(K, 3) camera centres of world_to_camera (K, 4, 4)."""
    return -np.einsum("kji,kj->ki", world_to_camera[:, :3, :3], world_to_camera[:, :3, 3])


def fit_similarity(world_to_camera: np.ndarray, rotation: np.ndarray, translation: np.ndarray,
                   depth: float | None = None) -> Similarity:
    """The similarity of the world whose motion of the cameras best matches small pose corrections
    rotation (K, 3) axis-angle radians and translation (K, 3) world units, in camera coordinates, of K
    cameras with stated world_to_camera (K, 4, 4): least squares over the K cameras, first order in the
    corrections, about the cameras' mean centre. The turns are weighted by a length so that both terms
    are lengths: `depth` (world units) when given, which measures a turn by how far it moves the
    pictures of points at that depth (a turn of a camera moves them by depth times its angle, a shift by
    its length); else the rig's radius."""
    r = world_to_camera[:, :3, :3]
    centres = _centres(world_to_camera)
    d = centres - centres.mean(0)
    radius = float(np.sqrt((d * d).sum(1).mean()))
    weight = depth if depth is not None else radius if radius > 1e-9 else 1.0
    turn = -np.einsum("kji,kj->ki", r, rotation)      # a_c = -R_c^T w_c
    move = -np.einsum("kji,kj->ki", r, translation)   # dC_c = -R_c^T t_c
    rows, rhs = [], []
    for k in range(len(r)):
        rows.append(np.hstack([weight * np.eye(3), np.zeros((3, 1)), np.zeros((3, 3))]))
        rhs.append(weight * turn[k])
        rows.append(np.hstack([-cross_matrix(d[k]), d[k][:, None], np.eye(3)]))
        rhs.append(move[k])
    x = np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)[0]
    return Similarity(x[:3], float(x[3]), x[4:], centres.mean(0))


def gauge_part(world_to_camera: np.ndarray, rotation: np.ndarray, translation: np.ndarray,
               depth: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The part of small pose corrections that is a similarity of the whole world (module docstring):
    (rotation (K, 3), translation (K, 3)) to subtract from the corrections rotation (K, 3) axis-angle
    radians and translation (K, 3) world units, both in camera coordinates, of K cameras with stated
    world_to_camera (K, 4, 4) (fit_similarity, with its `depth`)."""
    return fit_similarity(world_to_camera, rotation, translation, depth).corrections(world_to_camera)


def gauge_projector(world_to_camera: np.ndarray, depth: float | None = None) -> np.ndarray:
    """(6K, 6K) matrix P of `gauge_part` for K cameras with stated world_to_camera (K, 4, 4): with
    x = concat(rotation.ravel(), translation.ravel()) (rotation, translation (K, 3) as there), P @ x is
    the gauge part in the same layout. gauge_part is linear in the corrections, so P is built from it
    column by column, once; applying it needs no least-squares solve (on a GPU: no copy to the host)."""
    k = len(world_to_camera)
    basis = np.eye(6 * k)
    columns = [np.concatenate([part.ravel() for part in gauge_part(world_to_camera, e[:3 * k].reshape(k, 3),
                                                                  e[3 * k:].reshape(k, 3), depth)]) for e in basis]
    return np.stack(columns, axis=1)


def corrections_between(estimated: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rotation (K, 3), translation (K, 3)): the corrections D_c (module docstring) that take the
    reference world_to_camera (K, 4, 4) to the estimated ones (K, 4, 4): estimated = D_c reference."""
    delta = np.einsum("kij,kjl->kil", estimated, np.linalg.inv(reference))
    return np.stack([rotation_vector(d[:3, :3]) for d in delta]), delta[:, :3, 3].copy()


def similarity_between(estimated: np.ndarray, truth: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """The similarity of the world (scale s, rotation R (3, 3), shift t (3,); x_truth = s R x_est + t)
    that takes cameras posed at world_to_camera `estimated` (K, 4, 4) onto `truth` (K, 4, 4), exactly
    (not to first order): R the rotation nearest to the mean of the cameras' R_truth^T R_est (their
    orientations agree), then s and t by least squares on the camera centres. For K >= 2 cameras in
    any two gauges, such as a calibration's and the truth's."""
    estimated, truth = np.asarray(estimated, np.float64), np.asarray(truth, np.float64)
    u, _, vt = np.linalg.svd(np.einsum("kji,kjl->il", truth[:, :3, :3], estimated[:, :3, :3]))
    rotation = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
    a, b = _centres(estimated) @ rotation.T, _centres(truth)
    da, db = a - a.mean(0), b - b.mean(0)
    scale = float((da * db).sum() / max((da * da).sum(), 1e-300))
    return scale, rotation, b.mean(0) - scale * a.mean(0)


def aligned_pose_errors(estimated: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rotation errors (K,) degrees, position errors (K,) in the truth's units) of cameras at
    world_to_camera `estimated` (K, 4, 4) against `truth` (K, 4, 4) once `estimated` is moved by
    similarity_between."""
    scale, rotation, shift = similarity_between(estimated, truth)
    centres = scale * _centres(np.asarray(estimated, np.float64)) @ rotation.T + shift
    turned = np.einsum("kij,lj->kil", np.asarray(estimated, np.float64)[:, :3, :3], rotation)  # R_est R^T
    delta = np.einsum("kij,klj->kil", turned, np.asarray(truth, np.float64)[:, :3, :3])
    cos = (np.trace(delta, axis1=1, axis2=2) - 1) / 2
    sin = np.linalg.norm(np.stack([delta[:, 2, 1] - delta[:, 1, 2], delta[:, 0, 2] - delta[:, 2, 0],
                                   delta[:, 1, 0] - delta[:, 0, 1]], axis=1), axis=1) / 2
    angles = np.degrees(np.arctan2(sin, cos))
    return angles, np.linalg.norm(centres - _centres(np.asarray(truth, np.float64)), axis=1)
