"""Shared test settings: the coarse mesh of the findings tests and the usual unit modes.

Meshes are cached by the library per geometry, so building a twin of a geometry seen
before costs milliseconds.
"""

import math

import pytest
import yaml

from dea_array_twin import ArrayConfig, ArrayTwin

#: Unit 2 driven, its neighbours free: the paper's "neighbours not deflected".
FREE_CENTRE = ("free", "driven", "free")
#: A coarse mesh (344 P2 elements on the default array, against 974), fast enough for tests
#: that solve many curves.  Against the default mesh (docs/paper.md, "The mesh behind the
#: tests"): forces within 0.19 %, capacitance changes within 0.37 %, coupling indices within
#: 0.09 points; DE2 at 15 mm, neighbours free: force 0.14 %, capacitance 0.07 %.
COARSE = {"mesh_size": 20e-3, "mesh_size_indenter": 2.5e-3, "mesh_size_electrode": 5e-3}
#: A bistable dome under the circular unit, as a config's table bias entry:
#: B = 0.2035 + 0.08 tanh((w - 7 mm) / 1 mm) N on 0-16 mm (test/model/test_actuator.py
#: describes its branches); also the measured characteristic of the bias-design tests.
DOME_W = [0.0005 * i for i in range(33)]
DOME = {"type": "table", "position": DOME_W, "force": [0.2035 + 0.08 * math.tanh((w - 0.007) / 0.001) for w in DOME_W]}



def coarse_point_maps(count: int, seed: int):
    """Point maps of ``count`` random quadrature points of the coarse array over ``[1, d, q]`` (a flat state,
    2 lifting-like and 5 random vectors) and 3 enrichment vectors, with random positive weights: the
    reduced model's kernels' inputs without training one.  Returns ``(model, fmap, wmap, xi, unit)``."""
    import numpy as np

    from dea_array_twin.model import rom_kernels
    from dea_array_twin.model.membrane import MembraneModel

    model = MembraneModel(ArrayConfig(**COARSE))
    rng = np.random.default_rng(seed)
    ne, nq = model.disc.weight.shape
    flat = np.flatnonzero(rng.permutation(ne * nq) < count)
    elements, points = np.divmod(flat, nq)
    vectors = np.hstack([model.flat_state()[:, None], 1e-3 * rng.normal(size=(model.disc.n_dofs, 7))])
    fmap = rom_kernels.point_maps(model.disc, elements, points, vectors)
    wmap = rom_kernels.point_maps(model.disc, elements, points, 1e-3 * rng.normal(size=(model.disc.n_dofs, 3)))
    xi = model.thickness * model.disc.weight[elements, points] * rng.uniform(0.5, 2.0, elements.size)
    unit = np.ascontiguousarray(model.mesh.element_unit[elements])
    return model, fmap, wmap, xi, unit


@pytest.fixture
def make_twin():
    """``make_twin(settings=None, **config_changes)`` -> a fresh ArrayTwin."""

    def make(settings=None, **changes):
        return ArrayTwin(ArrayConfig(**changes), settings)

    return make


@pytest.fixture(scope="session")
def coarse_rom(tmp_path_factory):
    """A small reduced model of the coarse 1-by-3 array, trained once per session (about 26 FE snapshots).

    Every unit driven, d in [0, 8] mm, units 2 and 3 up to 2500 V and unit 1 never
    energised (so "voltage on an untrained unit" is outside its envelope); 14 modes,
    tolerance 2e-3.  Returns ``(config, rom, rom_file, config_yaml)``.
    """
    import numpy as np

    from dea_array_twin.model.reduced import Envelope
    from dea_array_twin.rom.train import train
    from dea_array_twin.romfile import save_rom

    cfg = ArrayConfig(**COARSE)
    envelope = Envelope(("driven",) * 3, np.zeros(3), np.full(3, 0.008), np.zeros(3), np.array([0.0, 2500.0, 2500.0]))
    rom = train(cfg, envelope, n_snapshots=26, n_modes=14, tolerance=2e-3, n_validation=6, seed=3).rom
    folder = tmp_path_factory.mktemp("rom")
    config_yaml = folder / "coarse.yaml"
    config_yaml.write_text(yaml.safe_dump(COARSE))
    return cfg, rom, save_rom(rom, folder / "coarse"), config_yaml


@pytest.fixture
def coarse_yaml(tmp_path):
    """A config YAML of the default array on the coarse mesh."""
    path = tmp_path / "coarse.yaml"
    path.write_text(yaml.safe_dump(COARSE))
    return path


class OutputLines:
    """The lines a subprocess prints, read by a thread, so a test can wait for one with a deadline.

    ``proc.stdout.readline()`` blocks until the process prints or exits, which defeats
    any deadline around it; :meth:`wait_for` does not.
    """

    def __init__(self, stream):
        import queue
        import threading

        self.lines: list[str] = []
        self._queue: "queue.Queue[str | None]" = queue.Queue()
        self._thread = threading.Thread(target=self._read, args=(stream,), daemon=True)
        self._thread.start()

    def _read(self, stream) -> None:
        for line in iter(stream.readline, ""):
            self._queue.put(line)
        self._queue.put(None)  # end of output

    def wait_for(self, predicate, timeout: float) -> bool:
        """Collect lines until ``predicate(self.lines)`` holds (True) or ``timeout`` s pass or output ends (False)."""
        import queue
        import time

        deadline = time.monotonic() + timeout
        while not predicate(self.lines):
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            try:
                line = self._queue.get(timeout=left)
            except queue.Empty:
                return False
            if line is None:
                return predicate(self.lines)
            self.lines.append(line)
        return True


def run_until_then_interrupt(args: list[str], until, timeout: float, **popen) -> tuple[OutputLines, bool, int]:
    """Run ``args`` in a ROS domain of its own (discovery on localhost, unbuffered output), wait up to
    ``timeout`` s for ``until(lines)`` on its output, then SIGINT it.

    Returns the output (with the lines the pipe still held after the exit), whether ``until`` held,
    and the exit code after SIGINT; a process that outlives this is killed.
    """
    import os
    import signal
    import subprocess

    from domain_coordinator import domain_id

    with domain_id() as domain:
        env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                   PYTHONUNBUFFERED="1")
        proc = subprocess.Popen(args, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, **popen)
        with proc:  # closes the pipe when done
            try:
                output = OutputLines(proc.stdout)
                held = output.wait_for(until, timeout)
                proc.send_signal(signal.SIGINT)
                code = proc.wait(timeout=30)
                output.wait_for(lambda lines: False, timeout=1.0)  # the last lines the pipe still holds
            finally:
                if proc.poll() is None:
                    proc.kill()
    return output, held, code
