"""The capacitance-only controller's position errors, ignoring or compensating the coupling.

Run:  .venv/bin/python tools/controller_figure.py [--out docs/img/actuator_controller.png] [--coarse]

Every unit of the 1-by-3 on the NBS of docs/actuator.md's figure 5 (-20.02 N/m, free at
-0.477 mm), released at 5 mm; quasi-static twin, control period 50 ms, integral gain
1e10 V^2/(m s).  Two scenarios, each with the coupling ignored and compensated
(:mod:`dea_array_twin.ros.stroke_controller`):

* hold: unit 2 held 1 mm above its rest; units 1 and 3 at rest for 3 s, then 2 mm up;
* wave: a 1.6 mm stroke wave of period 8 s on top of 0.8 mm through the three units, two
  periods (the offset keeps every set-point above where the neighbours alone lift a unit:
  the voltage only pushes).

Prints the numbers docs/actuator.md quotes and writes the figure.
"""

from __future__ import annotations

import argparse

import numpy as np

from dea_array_twin import ArrayConfig, ArrayTwin
from dea_array_twin.model.response import rest_state
from dea_array_twin.ros.stroke_controller import StrokeLoop, build_sensing_model, run_loop, wave_targets

NBS = {"type": "linear", "stiffness": -20.02, "free_position": -0.000477}
START, AMPLITUDE, V_MAX, DT, GAIN = 0.005, 0.002, 2730.0, 0.05, 1e10
COARSE = {"mesh_size": 20e-3, "mesh_size_indenter": 2.5e-3, "mesh_size_electrode": 5e-3}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="docs/img/actuator_controller.png")
    parser.add_argument("--coarse", action="store_true", help="the tests' coarse mesh (faster)")
    args = parser.parse_args()
    cfg = ArrayConfig.from_dict({**(COARSE if args.coarse else {}), "unit_modes": ["biased"], "bias": [NBS]})
    model = build_sensing_model(cfg, V_MAX, np.linspace(-0.5, 1.5, 17) * AMPLITUDE, levels=11, start=START)
    print(f"rest [mm]: {np.round(model.rest * 1e3, 4)}")
    print(f"dC_k/dw_j [pF/mm]:\n{np.round(model.coupling * 1e9, 4)}")
    print(f"dC_k/d(V_j^2) [pF/kV^2]:\n{np.round(model.voltage_coupling * 1e18, 4)}")

    def hold(t):
        up = AMPLITUDE if t >= 3.0 else 0.0
        return model.rest + np.array([up, 0.5 * AMPLITUDE, up])

    def wave(t):
        return wave_targets(t, model.rest, 0.8 * AMPLITUDE, 8.0, offset=0.4 * AMPLITUDE)

    runs = {}
    for name, targets, duration in (("hold", hold, 6.0), ("wave", wave, 16.0)):
        for compensate in (False, True):
            twin = ArrayTwin(cfg)
            rest_state(twin, start=START)
            runs[name, compensate] = run_loop(twin, StrokeLoop(model, compensate, GAIN, V_MAX), targets, duration, DT)
    for compensate in (False, True):
        label = "compensating" if compensate else "ignoring"
        run = runs["hold", compensate]
        print(f"hold, {label} coupling: unit 2 error with the neighbours at rest {1e3 * run.error[59, 1]:+.4f} mm, "
              f"up {1e3 * run.error[-1, 1]:+.4f} mm; its voltage {run.voltage[-1, 1]:.0f} V")
        run = runs["wave", compensate]
        second = run.time > 8.0
        rms = 1e3 * np.sqrt((run.error[second] ** 2).mean(axis=0))
        peak = 1e3 * np.abs(run.error[second]).max(axis=0)
        sensing = 1e3 * np.sqrt(((run.estimate - run.sensed)[second] ** 2).mean(axis=0))
        print(f"wave, {label} coupling (second period): position error RMS {np.round(rms, 4)} mm, "
              f"max {np.round(peak, 4)} mm; estimate error RMS {np.round(sensing, 4)} mm")
    _plot(runs, args.out)
    print(f"wrote {args.out}")


def _plot(runs, path: str) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(12, 4.8), layout="constrained")
    FigureCanvasAgg(fig)
    ax_hold, ax_wave = fig.subplots(1, 2)
    for compensate, style in ((False, "-"), (True, "--")):
        label = "coupling compensated" if compensate else "coupling ignored"
        run = runs["hold", compensate]
        ax_hold.plot(run.time, 1e3 * run.error[:, 1], style, color="tab:red", label=f"unit 2 error, {label}")
        run = runs["wave", compensate]
        for k, colour in enumerate(("tab:blue", "tab:orange", "tab:green")):
            ax_wave.plot(run.time, 1e3 * run.error[:, k], style, color=colour,
                         label=f"unit {k + 1}, {label}" if k == 1 or not compensate else None)
    run = runs["hold", False]
    twin_ax = ax_hold.twinx()
    twin_ax.plot(run.time, 1e3 * (run.position[:, 0] - run.position[0, 0]), ":", color="0.4")
    twin_ax.set_ylabel("unit 1 and 3 stroke [mm] (dotted)")
    ax_hold.set(xlabel="time [s]", ylabel="position error [mm]",
                title="(a) unit 2 held 1 mm up while units 1 and 3 rise 2 mm")
    ax_wave.set(xlabel="time [s]", ylabel="position error [mm]",
                title="(b) a stroke wave 0.8 -> 2.4 mm, period 8 s")
    for ax in (ax_hold, ax_wave):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    main()
