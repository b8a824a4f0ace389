"""Reduced-order model tools: training a ROM from FE snapshots and validating it against the FE.

The reduced model's numerics live in :mod:`dea_array_twin.model` (:mod:`~.model.reduced`,
:mod:`~.model.rom_build`, :mod:`~.model.reduced_twin`); ROM files are read and written by
:mod:`dea_array_twin.romfile`.  This layer adds what needs executors and progress:
sampling the envelope, solving the snapshots in parallel, validation
(:mod:`.train`).  May import the model, the file readers and the executors; not ROS,
bags, studies, calibration or replay.
"""

from .train import SnapshotResult, SnapshotTask, TrainingResult, Validation, solve_snapshots, train, validate

__all__ = ["SnapshotResult", "SnapshotTask", "TrainingResult", "Validation", "solve_snapshots", "train", "validate"]
