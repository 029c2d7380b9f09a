"""Unit quaternions (w, x, y, z), the convention of every observation in this package: w >= 0."""
from __future__ import annotations

import numpy as np

__all__ = ["rotation_to_quaternion", "quat_mul", "quat_conj", "quat_rotate"]


def rotation_to_quaternion(R) -> np.ndarray:
    """(..., 3, 3) rotation matrices -> (..., 4) unit quaternions with w >= 0 (NaN in, NaN out)."""
    R = np.asarray(R, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        w = np.sqrt(np.maximum(0.0, 1.0 + R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2])) / 2
        x = np.sqrt(np.maximum(0.0, 1.0 + R[..., 0, 0] - R[..., 1, 1] - R[..., 2, 2])) / 2
        y = np.sqrt(np.maximum(0.0, 1.0 - R[..., 0, 0] + R[..., 1, 1] - R[..., 2, 2])) / 2
        z = np.sqrt(np.maximum(0.0, 1.0 - R[..., 0, 0] - R[..., 1, 1] + R[..., 2, 2])) / 2
        x = np.copysign(x, R[..., 2, 1] - R[..., 1, 2])
        y = np.copysign(y, R[..., 0, 2] - R[..., 2, 0])
        z = np.copysign(z, R[..., 1, 0] - R[..., 0, 1])
        q = np.stack([w, x, y, z], -1)
        q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    bad = ~np.isfinite(R).all(axis=(-1, -2))
    q[bad] = np.nan
    return q


def quat_mul(a, b) -> np.ndarray:
    w1, x1, y1, z1 = np.moveaxis(np.asarray(a, dtype=np.float64), -1, 0)
    w2, x2, y2, z2 = np.moveaxis(np.asarray(b, dtype=np.float64), -1, 0)
    return np.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], -1)


def quat_conj(q) -> np.ndarray:
    return np.asarray(q, dtype=np.float64) * np.array([1.0, -1.0, -1.0, -1.0])


def quat_rotate(q, v) -> np.ndarray:
    """Rotate vector(s) ``v`` by ``q``."""
    v = np.asarray(v, dtype=np.float64)
    qv = np.concatenate([np.zeros(v.shape[:-1] + (1,)), v], -1)
    return quat_mul(quat_mul(q, qv), quat_conj(q))[..., 1:]
