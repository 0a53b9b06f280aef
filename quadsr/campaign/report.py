"""A campaign's report.md and figures: error distributions per controller, failures and error against each
swept parameter, identification accuracy against sensors and excitation (learn-fly campaigns).

The error figure is the RMS of the 3-D position error after 5 s (m): the take-off transient is excluded,
as in every tracking table of quadsr; crashed and failed tasks count as failures, not as errors.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from quadsr.campaign.runner import CampaignRun  # noqa: E402

ERROR = "rms_after_5s_m"
BINS = 5  # bins of a swept numeric parameter in the failure-rate figure


def _fmt(v: Any) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def _group(rows: list[dict[str, Any]], key: str) -> dict[str, list[dict[str, Any]]]:
    out: dict[str, list[dict[str, Any]]] = {}
    for r in rows:
        out.setdefault(str(r.get(key)), []).append(r)
    return out


def _errors(rows: list[dict[str, Any]]) -> np.ndarray:
    v = np.array([r.get(ERROR) if r.get("status") == "ok" and r.get(ERROR) is not None else np.nan
                  for r in rows], float)
    return v[np.isfinite(v)]


def summary_table(rows: list[dict[str, Any]]) -> str:
    """Markdown: per controller and trajectory, tasks, failures, and the error's median / p90 / max [mm]."""
    lines = ["| controller | trajectory | tasks | ok | crashed | failed | median [mm] | p90 [mm] "
             "| max [mm] |",
             "|---|---|---|---|---|---|---|---|---|"]
    for ctrl, crow in sorted(_group(rows, "controller").items()):
        for traj, trows in sorted(_group(crow, "trajectory").items()):
            e = _errors(trows) * 1e3
            n = {s: sum(r.get("status") == s for r in trows) for s in ("ok", "crashed", "failed")}
            stats = [np.median(e), np.percentile(e, 90), e.max()] if e.size else [math.nan] * 3
            lines.append(f"| {ctrl} | {traj} | {len(trows)} | {n['ok']} | {n['crashed']} | {n['failed']} | "
                         + " | ".join(_fmt(float(s)) for s in stats) + " |")
    return "\n".join(lines)


def cdf_figure(rows: list[dict[str, Any]], path: Path) -> Path:
    """Cumulative distribution of the error after 5 s per controller (log x), failures at the top."""
    fig, ax = plt.subplots(figsize=(7.5, 4.8))
    for ctrl, crow in sorted(_group(rows, "controller").items()):
        e = np.sort(_errors(crow)) * 1e3
        if e.size == 0:
            continue
        frac = np.arange(1, e.size + 1) / len(crow)  # failures never reach 1
        ax.step(e, frac, where="post", label=f"{ctrl} ({len(crow) - e.size} failed of {len(crow)})")
    if ax.has_data():
        ax.set_xscale("log")
        ax.legend(fontsize=8, loc="lower right")
    else:
        ax.text(0.5, 0.5, "no task flew past 5 s without a failure", ha="center", transform=ax.transAxes)
    ax.set_xlabel("RMS position error after 5 s [mm] (log)")
    ax.set_ylabel("fraction of tasks")
    ax.set_ylim(0, 1.02)
    ax.grid(True, which="both", alpha=0.3)
    ax.set_title("Tracking error per controller (cumulative)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _numeric(rows: list[dict[str, Any]], name: str) -> bool:
    values = [r.get(name) for r in rows]
    return all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values) and \
        len({float(v) for v in values}) > 1


def parameter_figure(rows: list[dict[str, Any]], name: str, path: Path) -> Path:
    """Error after 5 s (top, log) and failure rate (bottom) against one swept parameter, per controller."""
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(7.5, 6.5), sharex=_numeric(rows, name))
    numeric = _numeric(rows, name)
    groups = sorted(_group(rows, "controller").items())
    for i, (ctrl, crow) in enumerate(groups):
        ok = [r for r in crow if r.get("status") == "ok" and r.get(ERROR) is not None]
        if numeric:
            x = np.array([float(r[name]) for r in ok])
            top.scatter(x, [r[ERROR] * 1e3 for r in ok], s=10, label=ctrl)
            allx = np.array([float(r[name]) for r in crow])
            edges = np.linspace(allx.min(), allx.max(), BINS + 1)
            idx = np.clip(np.digitize(allx, edges) - 1, 0, BINS - 1)
            failed = np.array([r.get("status") != "ok" for r in crow])
            rate = [failed[idx == b].mean() if np.any(idx == b) else np.nan for b in range(BINS)]
            bottom.plot(0.5 * (edges[:-1] + edges[1:]), rate, "o-", label=ctrl)
        else:
            cats = sorted({str(r.get(name)) for r in rows})
            pos = {c: j for j, c in enumerate(cats)}
            width = 0.8 / max(len(groups), 1)
            top.scatter([pos[str(r[name])] + i * width for r in ok], [r[ERROR] * 1e3 for r in ok], s=10,
                        label=ctrl)
            rate = [np.mean([r.get("status") != "ok" for r in crow if str(r.get(name)) == c] or [np.nan])
                    for c in cats]
            bottom.bar(np.arange(len(cats)) + i * width, rate, width, label=ctrl)
            bottom.set_xticks(np.arange(len(cats)) + 0.4 - width / 2, cats)
    if top.has_data():
        top.set_yscale("log")
        top.legend(fontsize=8)
    top.set_ylabel("RMS error after 5 s [mm]")
    top.grid(True, which="both", alpha=0.3)
    bottom.set_ylabel("failure rate (crash or failed)")
    bottom.set_ylim(-0.02, 1.02)
    bottom.set_xlabel(name)
    bottom.grid(True, alpha=0.3)
    fig.suptitle(f"Against {name}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def identification_figure(rows: list[dict[str, Any]], swept: list[str], path: Path) -> Path | None:
    """learn-fly: each target's R^2 on a second flight against sensors, excitation and swept values."""
    r2_cols = sorted({k for r in rows for k in r if k.startswith("r2_")})
    learned = [r for r in rows if any(r.get(c) is not None for c in r2_cols)]
    if not learned:
        return None
    names = [n for n in dict.fromkeys(("sensors", "profile", *swept))
             if len({str(r.get(n)) for r in learned}) > 1] or ["sensors"]
    fig, axes = plt.subplots(len(names), 1, figsize=(7.5, 3.2 * len(names)), squeeze=False)
    for ax, name in zip(axes[:, 0], names, strict=True):
        numeric = _numeric(learned, name)
        cats = sorted({str(r.get(name)) for r in learned})
        for j, col in enumerate(r2_cols):
            pts = [(r.get(name), r[col]) for r in learned if r.get(col) is not None]
            if numeric:
                x = [float(v) for v, _ in pts]
            else:
                x = [cats.index(str(v)) + 0.06 * (j - len(r2_cols) / 2) for v, _ in pts]
            ax.scatter(x, [y for _, y in pts], s=14, label=col[3:])
        if not numeric:
            ax.set_xticks(range(len(cats)), cats)
        ax.set_xlabel(name)
        ax.set_ylabel("validation R^2")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7, ncol=3)
    fig.suptitle("Identification accuracy on a second flight (learn-fly tasks)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_report(run: CampaignRun, command: str) -> Path:
    """report.md (and its PNGs) in the campaign's output folder."""
    out = run.out
    spec = run.spec
    rows = run.rows
    counts = run.counts()
    swept = [n for n in spec.parameter_names() if n not in ("controller",) and
             len({str(r.get(n)) for r in rows}) > 1]
    figures = [cdf_figure(rows, out / "error_cdf.png")]
    for name in swept:
        figures.append(parameter_figure(rows, name, out / f"against_{name.replace('.', '_')}.png"))
    ident = identification_figure(rows, swept, out / "identification.png")
    if ident is not None:
        figures.append(ident)
    lines = [f"# Campaign {spec.name}", "",
             f"Command: `{command}`  ", f"Campaign file: `{spec.source}`, seed {spec.seed}, pipeline "
             f"{spec.pipeline}, nominal vehicle `{Path(spec.vehicle).name}` (controllers and models are "
             "built for it; each task's SITL flies the task's vehicle).  ",
             f"Tasks: {len(run.tasks)} ({run.skipped} done in an earlier run); ok {counts['ok']}, crashed "
             f"{counts['crashed']}, failed {counts['failed']}.  ",
             f"Wall time of this run: {run.wall_s:.1f} s on {run.workers or 'no workers (nothing to run)'}.",
             "", "## Parameters", "", "| parameter | values |", "|---|---|"]
    for n, values in spec.grid.items():
        lines.append(f"| {n} | grid: {', '.join(_fmt(v) for v in values)} |")
    for n, value in spec.fixed.items():
        lines.append(f"| {n} | fixed: {_fmt(value)} |")
    for n, dist in spec.random.items():
        lines.append(f"| {n} | {dist.describe()}, {spec.samples} draws |")
    lines += ["", "## Tracking error after 5 s (ok tasks) and failures", "", summary_table(rows), "",
              "## Figures", ""]
    lines += [f"![{p.stem}]({p.name})" for p in figures]
    failures = [r for r in rows if r.get("status") != "ok"]
    if failures:
        lines += ["", "## Failures", "", "| task | controller | trajectory | status | reason |",
                  "|---|---|---|---|---|"]
        for r in failures[:50]:
            reason = str(r.get("reason", "")).replace("|", "/")[:200]
            lines.append(f"| {r['task_id']} | {r.get('controller')} | {r.get('trajectory')} | "
                         f"{r.get('status')} | {reason} |")
        if len(failures) > 50:
            lines.append(f"| ... | {len(failures) - 50} more in results.csv | | | |")
    lines += ["", "Tables: `results.parquet` and `results.csv` (one row per task; identical for any number "
              "of workers), `timings.csv` (wall times; machine-dependent).", ""]
    path = out / "report.md"
    path.write_text("\n".join(lines))
    return path
