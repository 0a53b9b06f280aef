"""The combined figures of report.md (PNG, Agg): Figs. 4 and 6 (tracking of every controller) and Fig. 5."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from quadsr.paper_run import TrackingRow


def _steps(row: TrackingRow) -> dict[str, np.ndarray] | None:
    if row.flight_dir is None or not (row.flight_dir / "steps.csv").is_file():
        return None
    path = row.flight_dir / "steps.csv"
    with path.open(encoding="utf-8") as fh:
        header = fh.readline().strip().split(",")
    data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    if data.size == 0:
        return None
    return {name: data[:, i] for i, name in enumerate(header)}


def _line_style(label: str) -> dict[str, Any]:
    from quadsr.paper_run import LEARNED_LABEL

    # the learned-model line is drawn wide and light so the true-model line on top of it stays visible
    return {"lw": 3.0, "alpha": 0.45} if label == LEARNED_LABEL else {"lw": 1.1}


def _flights(rows: Sequence[TrackingRow], case: str) -> Iterator[tuple[TrackingRow, dict[str, np.ndarray]]]:
    """The rows of one case that have logged steps, with their step columns."""
    for r in rows:
        if r.case == case:
            d = _steps(r)
            if d is not None:
                yield r, d


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def tracking_overlay_figure(rows: Sequence[TrackingRow], case: str, path: Path) -> Path:
    """Figs. 4 and 6: x, y, z [m, NED] and psi [rad] over t [s], desired and every controller on one case."""
    plt = _pyplot()
    fig, axes = plt.subplots(4, 1, figsize=(8.0, 9.5), sharex=True)
    names = (("ref_x", "true_x", "x [m]"), ("ref_y", "true_y", "y [m]"),
             ("ref_z", "true_z", "z [m] (NED, down)"), ("ref_yaw", "true_psi", "psi [rad]"))
    desired_drawn = False
    for r, d in _flights(rows, case):
        for ax, (ref, actual, label) in zip(axes, names, strict=True):
            if not desired_drawn:
                ax.plot(d["t"], d[ref], "--", color="k", lw=1.6, label="desired")
            ax.plot(d["t"], d[actual], label=r.label, **_line_style(r.label))
            ax.set_ylabel(label)
        desired_drawn = True
    for ax in axes:
        ax.grid(True, alpha=0.3)
    axes[0].legend(loc="best", fontsize=7)
    axes[-1].set_xlabel("t [s]")
    title = {"case1": "Case I (paper Fig. 4)", "case2": "Case II (paper Fig. 6)"}.get(case, case)
    fig.suptitle(f"Actual and desired x, y, z and psi: {title}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def paths3d_figure(rows: Sequence[TrackingRow], path: Path) -> Path:
    """Fig. 5: desired and actual 3-D paths of every controller, Case I left and Case II right, height up."""
    plt = _pyplot()
    cases = sorted({r.case for r in rows})
    fig = plt.figure(figsize=(6.5 * max(len(cases), 1), 6.0))
    for k, case in enumerate(cases, 1):
        ax = fig.add_subplot(1, len(cases), k, projection="3d")
        desired_drawn = False
        for r, d in _flights(rows, case):
            if not desired_drawn:
                ax.plot(d["ref_x"], d["ref_y"], -d["ref_z"], "--", color="k", lw=1.6, label="desired")
                desired_drawn = True
            ax.plot(d["true_x"], d["true_y"], -d["true_z"], label=r.label, **_line_style(r.label))
        ax.set_xlabel("x north [m]")
        ax.set_ylabel("y east [m]")
        ax.set_zlabel("height -z [m]")
        ax.set_title({"case1": "Case I", "case2": "Case II"}.get(case, case))
        ax.legend(loc="best", fontsize=7)
    fig.suptitle("Position tracking in 3-D space (paper Fig. 5)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
