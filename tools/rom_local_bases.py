"""Would bases local to each unit beat a global POD basis on a large array? A projection study.

Run from the repository root on a trained ROM of the array (its envelope, reference state
and liftings are reused; nothing of its basis):

    .venv/bin/python tools/rom_local_bases.py ROM.npz [--train 600] [--test 60] [--workers 2]

Solves ``--train`` and ``--test`` FE equilibria over the ROM's envelope (seeds 0 and 1),
takes their fluctuations ``y = x - x_ref - sum_k d_k L_k`` (what the POD modes carry), and
projects the test fluctuations on

- a global POD basis of the training fluctuations with ``r`` modes, and
- one POD basis of ``r_loc`` modes per unit cell (the nodes nearest to that unit's centre),
  the cells' bases side by side (each mode zero outside its cell);

and prints the largest out-of-plane error over the test states (relative to the largest
``|y_z|``), the RMS error (relative to the RMS of ``y``), and the columns a quadrature point
of the reduced model would read: ``r + nd`` for the global basis, the modes of the cells of
the point's element plus ``nd`` for the local ones (mean and largest over elements).  The
update of a hyper-reduced model costs about its points times those columns.  Not a test;
not a benchmark: the numbers behind docs/rom.md's "local bases" paragraph.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from dea_array_twin.model.config import ArrayConfig
from dea_array_twin.model.twin import ArrayTwin
from dea_array_twin.rom.train import solve_snapshots
from dea_array_twin.romfile import load_rom


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("rom", help="a trained ROM file of the array (.npz)")
    parser.add_argument("--train", type=int, default=600, help="training FE solves (default 600)")
    parser.add_argument("--test", type=int, default=60, help="test FE solves (default 60)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--global-modes", default="60,100,150,200,300")
    parser.add_argument("--local-modes", default="5,10,15,20,30,40")
    args = parser.parse_args()
    rom = load_rom(args.rom)
    cfg, env = ArrayConfig.from_dict(rom.config), rom.envelope
    tic = time.perf_counter()
    train, _, _ = solve_snapshots(cfg, env.modes, *env.sample(args.train, 0), workers=args.workers)
    test, _, _ = solve_snapshots(cfg, env.modes, *env.sample(args.test, 1), workers=args.workers)
    print(f"{train.force.shape[0]} training and {test.force.shape[0]} test FE solves in "
          f"{time.perf_counter() - tic:.0f} s")
    y = train.positions - rom.reference - train.displacement @ rom.lift.T
    y_test = test.positions - rom.reference - test.displacement @ rom.lift.T
    n_test, nd = y_test.shape[0], rom.lift.shape[1]
    z_scale = np.abs(y_test.reshape(n_test, -1, 3)[:, :, 2]).max()
    rms_scale = np.sqrt((y_test**2).mean())

    def errors(projected: np.ndarray) -> str:
        e = (y_test - projected).reshape(n_test, -1, 3)
        return f"max z error {np.abs(e[:, :, 2]).max() / z_scale:.2e}, RMS {np.sqrt((e**2).mean()) / rms_scale:.2e}"

    _, _, vt = np.linalg.svd(y, full_matrices=False)
    for r in map(int, args.global_modes.split(",")):
        v = vt[:r].T
        print(f"global, r = {r}: {errors(y_test @ v @ v.T)}; columns per point {r + nd}")
    mesh = ArrayTwin(cfg).model.mesh
    centres = mesh.nodes[mesh.centre_nodes]
    cell = np.argmin(((mesh.nodes[:, None, :] - centres[None]) ** 2).sum(-1), axis=1)
    cells_per_element = np.array([np.unique(cell[e]).size for e in mesh.elements])
    dofs = [(3 * np.flatnonzero(cell == c)[:, None] + np.arange(3)).ravel() for c in range(centres.shape[0])]
    local_vt = [np.linalg.svd(y[:, d], full_matrices=False)[2] for d in dofs]
    for r in map(int, args.local_modes.split(",")):
        projected = np.zeros_like(y_test)
        for d, v in zip(dofs, local_vt):
            projected[:, d] = y_test[:, d] @ v[:r].T @ v[:r]
        print(f"local, r_loc = {r} per cell ({r * len(dofs)} in all): {errors(projected)}; columns per point "
              f"mean {r * cells_per_element.mean() + nd:.0f}, largest {r * cells_per_element.max() + nd}")


if __name__ == "__main__":
    main()
