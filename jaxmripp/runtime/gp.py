"""NumPy port of `jaxmripp.sim.gp`: the same fixed-capacity GP, update for update.

Same kernel (Matern-1/2 over (x, y, z) plus the heading on a circle of radius
heading_scale), same square root R of the inverse kernel matrix extended by one border row
per point, same first-in first-out eviction by one Householder reflection, same float32
arithmetic in the same order, so predictions agree with the JAX GP to float32 rounding
(see `jaxmripp.sim.gp` for the derivation). Only what a robot needs onboard is here: `add`
and `predict`; the covariance trace over an evaluation set (a training reward) is kept only
when evaluation poses are given.
"""

from __future__ import annotations

import numpy as np

from jaxmripp.runtime.mapping import HEADING_ANGLES
from jaxmripp.runtime.weights import GPSpec

F32 = np.float32


def _features(poses: np.ndarray, heading_scale: float) -> np.ndarray:
    """(N, 4) poses -> (5, N): x, y, z, heading_scale * (cos, sin) of the heading."""
    angle = poses[:, 3]
    return np.stack([poses[:, 0], poses[:, 1], poses[:, 2],
                     heading_scale * np.cos(angle), heading_scale * np.sin(angle)])


def kernel(a: np.ndarray, b: np.ndarray, spec: GPSpec) -> np.ndarray:
    """(A, 4), (B, 4) float32 poses -> (A, B) float32 covariances (jaxmripp.sim.gp.kernel)."""
    fa, fb = _features(a, spec.heading_scale), _features(b, spec.heading_scale)
    dist2 = np.square(fa[0][:, None] - fb[0][None, :])
    for c in range(1, 5):
        dist2 += np.square(fa[c][:, None] - fb[c][None, :])
    # Differences, not |a|^2 + |b|^2 - 2 a.b: near-duplicate poses must keep k ~ variance.
    return (spec.variance * np.exp(-np.sqrt(dist2) / spec.length_scale)).astype(F32, copy=False)


class GaussianProcess:
    """One GP over poses with capacity H; see jaxmripp.sim.gp.GPState for the fields."""

    def __init__(self, spec: GPSpec, eval_poses: np.ndarray | None = None):
        h = spec.capacity
        self.spec = spec
        self.inputs = np.zeros((h, 4), F32)
        self.targets = np.zeros((h,), F32)
        self.valid = np.zeros((h,), bool)
        self.root = np.zeros((h, h), F32)
        self.stamp = np.full((h,), -1, np.int32)
        self.count = 0
        self.eval_poses = None if eval_poses is None else np.asarray(eval_poses, F32)
        if self.eval_poses is not None:
            m = self.eval_poses.shape[0]
            self.eval_cross = np.zeros((h, m), F32)
            self.trace = F32(m * spec.variance)

    @property
    def size(self) -> int:
        """Points currently held."""
        return int(self.valid.sum())

    def add(self, pose, value) -> None:
        """Adds (pose (4,), value); when full, the oldest point goes first (jaxmripp.sim.gp.add)."""
        spec, h = self.spec, self.spec.capacity
        x = np.asarray(pose, F32).reshape(4)
        slot = self.count % h
        occupied = bool(self.valid[slot])
        root = self.root
        if occupied:
            # Householder reflection mapping column `slot` of R onto e_slot, then drop the
            # row and column (v = r + sign(r_j) |r| e_j avoids cancellation).
            r = root[:, slot]
            a = root.T @ r
            r_norm2 = np.sum(r * r)
            v = r.copy()
            v[slot] += (F32(-1.0) if r[slot] < 0 else F32(1.0)) * np.sqrt(r_norm2)
            v_norm2 = np.sum(v * v)
            root = root - np.outer((F32(2.0) / v_norm2) * v, v @ root)
            root[slot, :] = 0.0
            root[:, slot] = 0.0
        else:
            root = root.copy()
        self.valid[slot] = False

        # Border row for the new point in the same slot.
        k = kernel(x[None], self.inputs, spec)[0]
        k[~self.valid] = 0.0
        l = root @ k
        s = np.maximum(spec.variance + spec.noise - np.sum(l * l), F32(spec.noise)).astype(F32)
        b = root.T @ l
        row = -b
        row[slot] += F32(1.0)
        root[slot, :] = row / np.sqrt(s)

        if self.eval_poses is not None:
            m = self.eval_poses.shape[0]
            ab = np.stack([a if occupied else np.zeros_like(b), b]) @ self.eval_cross
            cross = kernel(x[None], self.eval_poses, spec)[0]
            rise = np.sum(ab[0] * ab[0]) / r_norm2 if occupied else F32(0.0)
            trace = self.trace + rise - np.sum(np.square(cross - ab[1])) / s
            self.trace = F32(np.clip(trace, 0.0, m * spec.variance))
            self.eval_cross[slot] = cross

        self.root = root
        self.inputs[slot] = x
        self.targets[slot] = F32(value)
        self.valid[slot] = True
        self.stamp[slot] = self.count
        self.count += 1

    def predict(self, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Posterior mean (L,) and latent variance (L,) in [0, variance] at poses (L, 4)."""
        poses = np.asarray(poses, F32)
        k = kernel(poses, self.inputs, self.spec)
        k[:, ~self.valid] = 0.0
        proj = k @ self.root.T
        mean = proj @ (self.root @ self.targets)
        variance = self.spec.variance - np.sum(proj * proj, axis=-1)
        return mean.astype(F32, copy=False), np.clip(variance, 0.0, self.spec.variance).astype(F32)


def evaluation_poses(spec: GPSpec) -> np.ndarray:
    """(M, 4) the trace evaluation set of jaxmripp.sim.gp.evaluation_poses."""
    g = spec.eval_grid
    centres = (np.arange(g, dtype=F32) + F32(0.5)) / F32(g)
    grid = np.stack(np.meshgrid(centres, centres, centres, indexing="ij"), axis=-1).reshape(-1, 3)
    positions = np.repeat(grid, len(HEADING_ANGLES), axis=0)
    angles = np.tile(HEADING_ANGLES, len(grid))[:, None]
    return np.concatenate([positions, angles], axis=1).astype(F32)
