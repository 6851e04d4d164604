"""``liris datasets check --plot``: the path with the findings, and the time steps."""

from __future__ import annotations

import numpy as np

from lidar_iris_eval.plotting import style

#: marker colour per kind of finding
FINDING_COLORS = {"scan gap": "#0072B2", "pose gap": "#56B4E9", "stationary span": "#E69F00",
                  "pseudo-revisit": "#CC79A7", "speed jump": "#D55E00",
                  "yaw-rate jump": "#009E73", "duplicate stamp": "#000000"}


def sequence_check_figure(xy: np.ndarray, steps: np.ndarray | None, findings: list[dict],
                          pseudo: np.ndarray | None = None, speed: np.ndarray | None = None,
                          max_speed: float | None = None, stationary_speed: float | None = None):
    """Three panels: the path (x-y, LiDAR frame) with every finding's frames marked,
    the time step between consecutive scans (log scale) with gaps and duplicates
    marked, and the speed per step with the platform limit and the stationary threshold.

    Parameters
    ----------
    xy : ``(N, 2)`` LiDAR-frame ground-plane positions.
    steps : ``(N - 1,)`` seconds between scans, or None without times.
    findings : :attr:`~lidar_iris_eval.evaluation.sequence_check.CheckReport.findings`.
    pseudo : ``(N,)`` bool pseudo-revisit queries, or None.
    speed : ``(N - 1,)`` m/s per step, or None; max_speed, stationary_speed: m/s lines.
    """
    xy = np.asarray(xy, dtype=np.float64)
    with style.context():
        fig = style.new_figure(2 * style.COLUMN_WIDTH, 4.6)
        grid = fig.add_gridspec(2, 2, width_ratios=(1.0, 1.3))
        ax_path = fig.add_subplot(grid[:, 0])
        ax_dt = fig.add_subplot(grid[0, 1])
        ax_speed = fig.add_subplot(grid[1, 1], sharex=ax_dt)
        ax_path.plot(xy[:, 0], xy[:, 1], color="0.65", linewidth=0.7, gid="path")
        ax_path.plot(xy[:1, 0], xy[:1, 1], marker="s", color="0.2", markersize=3,
                     linestyle="none", label="start")
        if pseudo is not None and np.any(pseudo):
            idx = np.flatnonzero(pseudo)
            ax_path.plot(xy[idx, 0], xy[idx, 1], "o", markersize=3, markerfacecolor="none",
                         color=FINDING_COLORS["pseudo-revisit"], gid="pseudo-revisit",
                         label="pseudo-revisit")
        seen = set()
        for f in findings:
            if f["frames"] is None or f["check"] == "pseudo-revisit":
                continue
            a, b = f["frames"]
            color = FINDING_COLORS.get(f["check"], "#000000")
            label = None if f["check"] in seen else f["check"]
            seen.add(f["check"])
            ax_path.plot(xy[a:b + 1, 0], xy[a:b + 1, 1], color=color, linewidth=2.2,
                         marker="x", markersize=3.5, gid=f"finding:{f['check']}", label=label,
                         zorder=3)
        ax_path.set_aspect("equal", adjustable="datalim")
        ax_path.set_xlabel("x [m] (LiDAR)")
        ax_path.set_ylabel("y [m] (LiDAR)")
        ax_path.tick_params(labelsize=6, length=2)
        ax_path.legend(fontsize=5, loc="best")
        if steps is not None and len(steps):
            shown = np.where(steps > 0, steps, np.nan)
            ax_dt.semilogy(np.arange(len(steps)), shown, color="0.3", linewidth=0.7, gid="steps")
            for f in findings:
                if f["check"] in ("scan gap", "duplicate stamp") and f["frames"] is not None:
                    k = f["frames"][0]
                    ax_dt.axvline(k, color=FINDING_COLORS[f["check"]], linewidth=0.8,
                                  linestyle="--", gid=f"step:{f['check']}")
            ax_dt.set_ylabel("time to next scan [s]")
        else:
            ax_dt.text(0.5, 0.5, "no scan times", ha="center", va="center",
                       transform=ax_dt.transAxes)
        ax_dt.tick_params(labelsize=6, length=2)
        if speed is not None and len(speed):
            ax_speed.plot(np.arange(len(speed)), speed, color="0.3", linewidth=0.7, gid="speed")
            for value, name, color in ((max_speed, "platform limit", "#D55E00"),
                                       (stationary_speed, "stationary below", "#E69F00")):
                if value is not None:
                    ax_speed.axhline(value, color=color, linewidth=0.8, linestyle="--",
                                     label=f"{name} {value:g} m/s")
            ax_speed.set_yscale("symlog", linthresh=0.1)
            ax_speed.set_ylim(bottom=0)
            ax_speed.legend(fontsize=5, loc="best")
        else:
            ax_speed.text(0.5, 0.5, "no speeds (no times)", ha="center", va="center",
                          transform=ax_speed.transAxes)
        ax_speed.set_xlabel("scan index")
        ax_speed.set_ylabel("speed [m/s]")
        ax_speed.tick_params(labelsize=6, length=2)
        n = len(findings)
        ax_path.set_title(f"{n} finding{'s' if n != 1 else ''}" if n else "clean: no finding",
                          fontsize=7, pad=2)
    return fig


def plot_sequence_check(data, report, path) -> str:
    """Write the figure of a check (``data``: a ``TimingInput``; ``report``: its result)."""
    poses = np.asarray(data.poses)
    steps = None if data.times is None else np.diff(np.asarray(data.times, dtype=np.float64))
    fig = sequence_check_figure(poses[:, :2, 3], steps, report.findings,
                                getattr(report, "pseudo", None), getattr(report, "speed", None),
                                report.summary.get("max_speed_m_s"),
                                report.limits.stationary_speed)
    return str(style.save(fig, path))
