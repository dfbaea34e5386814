"""The gray box's learned part ("dark gray"): a small correction of what the physics leaves.

Gaussian radial basis functions on a fixed grid over the training envelope (three levels along each
input that varies in the training data, at most 3^4 = 81), weighted by ridge regression: a convex
fit with a closed-form solution in float64, so the same data give the same model on any machine and
BLAS to far below the warning margin. Two guards keep it honest where it has not learned anything:

- fading: outside the envelope it is multiplied by exp(-sum((d_i / (FADE_SPAN * span_i))^2)), d_i the
  distance beyond the envelope along input i, so far outside only the physics speaks;
- bounded: the result is clipped to the largest magnitude it reached on the training points.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

LEVELS = (0.0, 0.5, 1.0)  # grid levels in the envelope's normalized coordinates
WIDTH = 0.5  # Gaussian width in normalized coordinates (the grid spacing)
RIDGE = 0.1  # ridge penalty relative to the mean diagonal of the Gram matrix
FADE_SPAN = 0.1  # the correction falls to 1/e this share of the envelope's span beyond it
MIN_SPAN_REL = 1e-6  # an input spanning less than this (relative) does not vary in the data


@dataclass(frozen=True)
class Correction:
    lo: NDArray[np.float64]  # (4,) envelope minimum of each model input
    span: NDArray[np.float64]  # (4,) its width (a floor for inputs that do not vary)
    active: NDArray[np.bool_]  # (4,) inputs that vary in the training data
    centers: NDArray[np.float64]  # (k, n_active) RBF centres in normalized coordinates
    weights: NDArray[np.float64]  # (k,) l/min
    bound_lpm: float

    def basis(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        z = ((x - self.lo) / self.span)[:, self.active]
        c = self.centers
        d2 = np.sum(z * z, axis=1)[:, None] - 2.0 * (z @ c.T) + np.sum(c * c, axis=1)[None, :]
        return np.exp(-d2 / (2.0 * WIDTH * WIDTH))

    def fade(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        hi = self.lo + self.span
        d = (np.maximum(self.lo - x, 0.0) + np.maximum(x - hi, 0.0)) / (FADE_SPAN * self.span)
        return np.exp(-np.sum(d * d, axis=1))

    def raw_lpm(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        return self.basis(x) @ self.weights

    def __call__(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        """The correction in l/min: faded outside the envelope, bounded."""
        return np.clip(self.raw_lpm(x) * self.fade(x), -self.bound_lpm, self.bound_lpm)


def envelope_box(x: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    lo, hi = x.min(axis=0), x.max(axis=0)
    floor = MIN_SPAN_REL * np.maximum(1.0, np.maximum(np.abs(lo), np.abs(hi)))
    active = (hi - lo) > floor
    return lo, np.where(active, hi - lo, floor), active


def fit(x: NDArray[np.float64], residual_lpm: NDArray[np.float64]) -> Correction:
    """Ridge regression of the residual flow on the grid's basis; ``x``: the training inputs."""
    lo, span, active = envelope_box(x)
    k = int(active.sum())
    centers = np.array(list(itertools.product(LEVELS, repeat=k)), dtype=float).reshape(-1, k)
    c = Correction(lo, span, active, centers, np.zeros(len(centers)), 0.0)
    phi = c.basis(x)
    gram = phi.T @ phi
    penalty = RIDGE * float(np.trace(gram)) / len(gram)
    weights = np.linalg.solve(gram + penalty * np.eye(len(gram)), phi.T @ residual_lpm)
    bound = float(np.max(np.abs(phi @ weights))) if len(x) else 0.0
    return Correction(lo, span, active, centers, weights, bound)
