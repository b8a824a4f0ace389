"""Goodness-of-fit measures shared by replay and calibration (no I/O, no ROS)."""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

__all__ = ["fit"]


def fit(measured: Sequence[float] | np.ndarray, model: Sequence[float] | np.ndarray) -> float:
    """Goodness of fit of a model signal to a measured one, paper eq. 12.

    ``FIT = 100 (1 - ||x - xm|| / ||x - mean(x)||)`` with ``x`` measured and ``xm``
    model: 100 for a perfect model, 0 for a model no better than the measured mean,
    negative for a worse one.

    Parameters
    ----------
    measured, model
        Samples of the same signal at the same instants (same shape; flattened).

    Returns
    -------
    float
        FIT in %; ``nan`` when undefined: no samples, or a constant measured signal
        (the denominator is zero).

    Raises
    ------
    ValueError
        The two signals differ in shape.
    """
    x = np.asarray(measured, dtype=float).ravel()
    xm = np.asarray(model, dtype=float).ravel()
    if x.shape != xm.shape:
        raise ValueError(f"measured and model must have the same shape, got {x.shape} and {xm.shape}")
    if x.size == 0 or np.all(x == x[0]):
        return math.nan
    spread = float(np.linalg.norm(x - x.mean()))
    if not spread > 0.0:  # zero or nan
        return math.nan
    return 100.0 * (1.0 - float(np.linalg.norm(x - xm)) / spread)
