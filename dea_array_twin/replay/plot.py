"""``dea-twin plot BAG -o run.png``: a recorded or replayed run at a glance.

Three stacked axes over time, one colour per unit: the commands (displacement [mm],
solid, left scale; voltage [V], dashed, right scale; drawn as held values), the
forces [N] and the capacitances [pF].  Reads any bag :class:`~dea_array_twin.bag.reader.Bag` opens: a
recording of the twin node, a rig's command bag (outputs then empty) or the MCAP
written by ``dea-twin replay``, through :func:`~dea_array_twin.bag.series.load_series` (topics chosen
as ``replay`` chooses them; times matching the replay's CSV).

Uses matplotlib's object-oriented API on the Agg canvas (no pyplot, no global
backend switch), so it runs headless and inside notebooks alike.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..bag.series import Series

__all__ = ["plot_series"]

#: Channel -> (axis label, factor from SI to the plotted unit).
_UNITS = {"displacement": ("displacement [mm]", 1e3), "voltage": ("voltage [V]", 1.0),
          "force": ("force [N]", 1.0), "capacitance": ("capacitance [pF]", 1e12)}


def plot_series(series: dict[str, Series], end_s: float, path: str | Path, title: str = "") -> Path:
    """Draw the three stacked axes and save them as a PNG.

    Parameters
    ----------
    series
        From :func:`load_series`.
    end_s
        Where the held commands end [s].
    path
        The image to write (its suffix picks the format; ``.png`` recommended).
    title
        Figure title.

    Returns
    -------
    Path
        ``path``.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

    n = max((s.values.shape[1] for s in series.values()), default=1)
    colours = [f"C{k % 10}" for k in range(n)]
    widths = np.linspace(2.6, 1.2, n) if n > 1 else [1.6]  # later units drawn thinner: overlaps stay visible
    fig = Figure(figsize=(10, 9), layout="constrained")
    FigureCanvasAgg(fig)
    ax_cmd, ax_force, ax_cap = fig.subplots(3, 1, sharex=True)
    ax_volt = ax_cmd.twinx()

    def draw(ax, kind: str, style: str) -> None:
        label, factor = _UNITS[kind]
        ax.set_ylabel(label)
        s = series.get(kind)
        if s is None:
            ax.text(0.5, 0.5, f"no {kind} messages in the bag", transform=ax.transAxes, ha="center",
                    va="center", color="0.5")
            return
        # every channel holds its value until the next message (sample and hold, quasi-static
        # outputs): steps, drawn on to the end of the recording
        t = np.append(s.time_s, max(end_s, s.time_s[-1]))
        v = np.vstack([s.values, s.values[-1:]]) * factor
        for k in range(v.shape[1]):
            ax.plot(t, v[:, k], style, color=colours[k], drawstyle="steps-post", lw=widths[k])

    draw(ax_cmd, "displacement", "-")
    if "voltage" in series:
        draw(ax_volt, "voltage", "--")
    else:
        ax_volt.set_visible(False)
    draw(ax_force, "force", "-")
    draw(ax_cap, "capacitance", "-")
    ax_cmd.set_title("commands (held)")
    ax_force.set_title("force on each indenter")
    ax_cap.set_title("capacitance of each unit")
    handles = [Line2D([], [], color=colours[k], lw=widths[k], label=f"unit {k + 1}") for k in range(n)]
    if "voltage" in series:
        handles += [Line2D([], [], color="k", ls="-", label="displacement\n(left scale)"),
                    Line2D([], [], color="k", ls="--", label="voltage\n(right scale)")]
    fig.legend(handles=handles, loc="outside right upper", fontsize="small")
    for ax in (ax_cmd, ax_force, ax_cap):
        ax.grid(True, alpha=0.3)
    ax_cap.set_xlabel("time [s]")
    sources = ", ".join(s.topic for s in series.values())
    fig.suptitle(f"{title}\n{sources}" if title else sources, fontsize="medium")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    return path
