"""The paper's tracking figures as PNG (Agg): x, y, z, psi vs desired (Figs. 4, 6), 3-D path (Fig. 5)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def tracking_figure(
    t: np.ndarray,
    position: np.ndarray,
    position_desired: np.ndarray,
    yaw: np.ndarray,
    yaw_desired: np.ndarray,
    path: str | Path,
    title: str = "",
) -> Path:
    """Write x, y, z [m, NED] and psi [rad] actual (solid) vs desired (dashed) against t [s] to a PNG, with a
    last panel of the 3-D position error [m] on a log scale (0.003 mm and 99 mm are not drawn on top of each
    other)."""
    fig, axes = plt.subplots(5, 1, figsize=(7.5, 11.0), sharex=True)
    names = ("x [m]", "y [m]", "z [m] (NED, down)", "psi [rad]")
    actual = [position[:, 0], position[:, 1], position[:, 2], yaw]
    desired = [position_desired[:, 0], position_desired[:, 1], position_desired[:, 2], yaw_desired]
    for ax, name, a, d in zip(axes[:4], names, actual, desired, strict=True):
        ax.plot(t, d, "--", color="tab:red", lw=1.4, label="desired")
        ax.plot(t, a, "-", color="tab:blue", lw=1.1, label="actual")
        ax.set_ylabel(name)
        ax.grid(True, alpha=0.3)
    axes[0].legend(loc="best", fontsize=8)
    error = np.linalg.norm(np.asarray(position, float) - np.asarray(position_desired, float), axis=1)
    ax = axes[4]
    ax.semilogy(t, np.maximum(error, 1e-9), "-", color="tab:purple", lw=1.0)
    ax.axhline(0.05, color="gray", ls=":", lw=1.0, label="5 cm")
    ax.set_ylabel("|error| [m] (log)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    axes[-1].set_xlabel("t [s]")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    out = Path(path)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def path3d_figure(position: np.ndarray, position_desired: np.ndarray, path: str | Path,
                  title: str = "") -> Path:
    """Write the actual and desired 3-D paths to a PNG, drawn with height up (-z NED)."""
    fig = plt.figure(figsize=(7.0, 6.0))
    ax = fig.add_subplot(111, projection="3d")
    ax.plot(position_desired[:, 0], position_desired[:, 1], -position_desired[:, 2], "--", color="tab:red",
            lw=1.4, label="desired")
    ax.plot(position[:, 0], position[:, 1], -position[:, 2], "-", color="tab:blue", lw=1.1, label="actual")
    ax.scatter([position[0, 0]], [position[0, 1]], [-position[0, 2]], color="k", s=12, label="start")
    ax.set_xlabel("x north [m]")
    ax.set_ylabel("y east [m]")
    ax.set_zlabel("height -z [m]")
    ax.legend(loc="best", fontsize=8)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    out = Path(path)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
