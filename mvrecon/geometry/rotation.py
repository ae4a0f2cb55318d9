"""Rotations as 3x3 matrices and Hamilton quaternions (w, x, y, z), COLMAP's convention."""

import numpy as np


def quat_to_rotmat(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a unit quaternion (w, x, y, z); the quaternion is normalised first."""
    w, x, y, z = np.asarray(q, dtype=float) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def rotmat_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) with w >= 0 of a rotation matrix: Eigen's (eigen_quaternions, stable near
    180 deg), normalised, so that a matrix read from a file with few digits still gives a unit quaternion."""
    q = eigen_quaternions(R)[0]
    q /= np.linalg.norm(q)
    return -q if q[0] < 0 else q


def eigen_quaternions(R: np.ndarray) -> np.ndarray:
    """(n,4) unit quaternions (w, x, y, z) of rotation matrices (n,3,3), computed as Eigen's Quaternion(matrix)
    does, operation for operation (w may be negative), so that written poses come out in the same bits as
    pycolmap's (io/colmap_model.py)."""
    R = np.asarray(R, dtype=np.float64).reshape(-1, 3, 3)
    q = np.empty((len(R), 4))  # x, y, z, w as Eigen stores them
    trace = R[:, 0, 0] + (R[:, 1, 1] + R[:, 2, 2])  # Eigen's sum order (it differs in the last bit otherwise)
    pos = trace > 0
    t = np.sqrt(trace[pos] + 1.0)
    q[pos, 3] = 0.5 * t
    t = 0.5 / t
    Rp = R[pos]
    q[pos, 0] = (Rp[:, 2, 1] - Rp[:, 1, 2]) * t
    q[pos, 1] = (Rp[:, 0, 2] - Rp[:, 2, 0]) * t
    q[pos, 2] = (Rp[:, 1, 0] - Rp[:, 0, 1]) * t
    rows = np.flatnonzero(~pos)
    diag = R[rows][:, [0, 1, 2], [0, 1, 2]]
    big = np.where(diag[:, 1] > diag[:, 0], 1, 0)  # the largest diagonal entry, first one on ties
    big = np.where(diag[:, 2] > diag[np.arange(len(rows)), big], 2, big)
    for i in range(3):
        r = rows[big == i]
        j, k = (i + 1) % 3, (i + 2) % 3
        t = np.sqrt(R[r, i, i] - R[r, j, j] - R[r, k, k] + 1.0)
        q[r, i] = 0.5 * t
        t = 0.5 / t
        q[r, 3] = (R[r, k, j] - R[r, j, k]) * t
        q[r, j] = (R[r, j, i] + R[r, i, j]) * t
        q[r, k] = (R[r, k, i] + R[r, i, k]) * t
    return q[:, [3, 0, 1, 2]]


def eigen_rotate(q: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Points X (n,3) turned by unit quaternions q (n,4; w, x, y, z) with Eigen's formula for q * v, the one
    COLMAP projects with: by R instead, all but 2 of templeSparseRing's 1699 point errors in points3D.bin
    differed in the last bits."""
    uv = np.cross(q[:, 1:], X)
    uv = uv + uv
    return X + q[:, :1] * uv + np.cross(q[:, 1:], uv)


def angle_axis_to_rotmat(rvec: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation by |rvec| radians about rvec."""
    rvec = np.asarray(rvec, dtype=float)
    theta = np.linalg.norm(rvec)
    if theta < 1e-12:
        return np.eye(3)
    k = rvec / theta
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(theta) * K + (1 - np.cos(theta)) * K @ K


def nearest_rotation(M: np.ndarray) -> np.ndarray:
    """The rotation nearest M in the Frobenius norm, or of each of a stack (..., 3, 3): U diag(1, 1, det(U V^T)) V^T
    of M's SVD. For M = sum b a^T over pairs of vectors it is the rotation R minimising sum |b - R a|^2 (Kabsch)."""
    U, _, Vt = np.linalg.svd(np.asarray(M, dtype=float))
    U = U.copy()
    U[..., :, 2] *= np.sign(np.linalg.det(U @ Vt))[..., None]
    return U @ Vt


def rotation_angle_deg(R: np.ndarray) -> float | np.ndarray:
    """Angle of a rotation matrix in degrees, or of each of a stack (..., 3, 3); atan2 of the skew and trace parts
    stays exact near zero, where arccos of the trace alone loses everything below about 1e-6 degrees."""
    R = np.asarray(R, dtype=float)
    skew = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], axis=-1)
    c = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    angle = np.degrees(np.arctan2(0.5 * np.linalg.norm(skew, axis=-1), c))
    return float(angle) if angle.ndim == 0 else angle


def rotation_error_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Angle of the rotation that takes R_b to R_a, in degrees."""
    return rotation_angle_deg(np.asarray(R_a) @ np.asarray(R_b).T)


def vector_angle_deg(a: np.ndarray, b: np.ndarray) -> float | np.ndarray:
    """Angle between two vectors in degrees, or between each pair of two stacks (..., 3); 180 where either is zero
    (an undefined direction counts as failed). atan2 of the cross and dot products, exact near zero as above."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    undefined = (np.linalg.norm(a, axis=-1) < 1e-15) | (np.linalg.norm(b, axis=-1) < 1e-15)
    angle = np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1)))
    angle = np.where(undefined, 180.0, angle)
    return float(angle) if angle.ndim == 0 else angle
