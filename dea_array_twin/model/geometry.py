"""Reference (unstretched) geometry of the array: frame and unit centres."""

from __future__ import annotations

import numpy as np

from .config import ArrayConfig


def unit_centres(cfg: ArrayConfig) -> np.ndarray:
    """Centres of the units in the reference plane [m, scaled], shape (n_units, 2).

    The grid is centred on the frame; units are numbered row by row starting at the
    top left (largest y, smallest x).  For the default 1-by-3 array the centres are
    at x = -35, 0, +35 mm.
    """
    if cfg.layout == "circular":
        return np.zeros((1, 2))
    pitch = cfg.pitch
    xs = (np.arange(cfg.cols) - 0.5 * (cfg.cols - 1)) * pitch
    ys = (0.5 * (cfg.rows - 1) - np.arange(cfg.rows)) * pitch
    gx, gy = np.meshgrid(xs, ys)
    return np.column_stack([gx.ravel(), gy.ravel()])


def edge_distance(cfg: ArrayConfig) -> float:
    """Smallest electrode-to-frame distance b [m, scaled] (paper's "b")."""
    centres = unit_centres(cfg)
    half = 0.5 * cfg.scaled("electrode_diameter")
    if cfg.electrode_shape == "square":
        half = 0.5 * cfg.square_side
    if cfg.layout == "circular":
        reach = half if cfg.electrode_shape == "circle" else half * np.sqrt(2.0)
        return cfg.scaled("frame_radius") - reach
    gaps_x = 0.5 * cfg.scaled("length") - np.abs(centres[:, 0]) - half
    gaps_y = 0.5 * cfg.scaled("width") - np.abs(centres[:, 1]) - half
    return float(min(gaps_x.min(), gaps_y.min()))
