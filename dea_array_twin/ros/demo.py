"""``dea-twin demo``: the twin node and the example wave controller in one process.

Both nodes run on one executor on the user's ROS domain, so ``ros2 topic echo
/force`` or Foxglove can watch too.  Twice a second it prints what the array does:
each unit's centre deflection, force and capacitance change.
"""

from __future__ import annotations

import sys
import time
from typing import Sequence

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor

from ..model.config import ConfigError
from .node import TwinNode
from .spin import init_ros, shutdown_signals, stopped_by_signal
from .wave_controller import WaveController


def _row(node: TwinNode, elapsed: float) -> str:
    res = node.result
    cells = [f"{elapsed:6.1f}"]
    for k in range(node.config.n_units):
        cells.append(f"{res.centre_deflection[k] * 1e3:6.2f} {res.force[k]:6.3f} "
                     f"{res.delta_capacitance[k] * 1e12:7.2f}")
    return " | ".join(cells)


def run_demo(node_args: Sequence[str], duration: float) -> int:
    """Run twin + wave controller for ``duration`` s (0 = until Ctrl-C); return the exit code."""
    nodes = []
    with shutdown_signals() as install_again:
        try:
            init_ros(list(node_args), "dea-twin demo")
        except SystemExit as exc:
            return int(exc.code)
        try:
            nodes.append(TwinNode())
            nodes.append(WaveController())
            install_again()
            executor = SingleThreadedExecutor()
            for node in nodes:
                executor.add_node(node)
            twin = nodes[0]
            n = twin.config.n_units
            print("t [s]  | " + " | ".join(f"unit {k + 1}: d [mm] F [N] dC [pF]" for k in range(n)), flush=True)
            start = last = time.monotonic()
            while rclpy.ok() and (duration <= 0 or time.monotonic() - start < duration):
                executor.spin_once(timeout_sec=0.05)
                if time.monotonic() - last >= 0.5 and twin.result is not None:
                    last = time.monotonic()
                    print(_row(twin, last - start), flush=True)
        except ConfigError as exc:
            print(f"dea-twin: error: {exc}", file=sys.stderr)
            return 2
        except (KeyboardInterrupt, ExternalShutdownException):
            pass
        except Exception:
            if not stopped_by_signal():
                raise
        finally:
            for node in nodes:
                node.destroy_node()
            rclpy.try_shutdown()
    return 0
