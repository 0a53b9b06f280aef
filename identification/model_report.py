"""The model report: report.md and fit.png for an engineer deciding whether to trust a learned model.

report.md: the data (flights, rows, what the segmentation kept), per target the validation metrics, the
equation in the display normal form grouped by physical meaning (identification.equation_form, DIGITS
significant digits), the plausibility checks (identification.plausibility) and the flags (low R^2 on the
validation rows; the engine's own notes and flags where the model file has them) and the engine's account of
its search (rounds, the ground-effect law at the rotor hubs and the hubs it found). fit.png: per target,
measured and predicted over time on the validation rows, and the residual (measured - predicted) below.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from bridge.errors import UserError
from identification.equation_form import DISPLAY_LEGEND, equation_text
from identification.metrics import table_metrics, weak_metrics
from identification.model_file import TARGET_INFO
from identification.plausibility import Check
from identification.table import TARGET_NAMES, Dataset
from identification.weak_form import WeakSettings, weak_rows

DIGITS = 3  # significant digits of the coefficients shown
LOW_R2 = 0.5  # validation R^2 below this is flagged


def model_flags(model: Any, validation: Dataset) -> list[str]:
    """Flags of a fitted model on validation rows: low R^2 per target, and the engine's own notes/flags."""
    flags = []
    pred = model.predict(validation)
    engine = getattr(getattr(model, "model_", None), "engine", {}) or {}
    op = None
    if "weak_form" in engine:  # learned in the weak form: judged there too (identification.weak_form)
        w = engine["weak_form"]
        op = weak_rows(validation.t, validation.flight,
                       WeakSettings(float(w["half_window_s"]), float(w["stride_s"]), int(w["power"])))
    for i, name in enumerate(model.target_names):
        y = validation.targets[:, TARGET_NAMES.index(name)]
        r2 = (table_metrics(y, pred[:, i]) if op is None else weak_metrics(y, pred[:, i], op))["r2"]
        if not r2 >= LOW_R2:
            flags.append(f"{name}: validation R^2 {r2:.3f} < {LOW_R2} (the model explains little of it)")
    for key in ("flags", "notes"):
        for item in engine.get(key, []) or []:
            flags.append(str(item))
    return flags


def search_lines(engine: dict[str, Any]) -> list[str]:
    """Markdown lines of the engine's per-target account of its search (model file `engine.stats`): rounds,
    pool, and the ground-effect law at the rotor hubs (kept or why not, the hubs it found in m FRD)."""
    lines = []
    for target, stats in (engine.get("stats") or {}).items():
        if not isinstance(stats, dict):
            continue
        parts = [f"{stats[k]} {label}" for k, label in (("rounds", "rounds"), ("pool", "features pooled"))
                 if k in stats]
        for key, label in (("hub_law", "hub law"), ("hub_law_refit", "hub law refit")):
            if key in stats:
                parts.append(f"{label}: {stats[key]}")
        hubs = stats.get("hub_offsets_m")
        if hubs:
            points = ", ".join("(" + ", ".join(f"{float(v):.3f}" for v in r) + ")" for r in hubs)
            parts.append(f"hubs at {points} m FRD from the CG (rotors 1-4)")
        if parts:
            lines.append(f"- {target}: " + "; ".join(parts))
    return lines


def _figure(model: Any, validation: Dataset, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(model.target_names)
    pred = model.predict(validation)
    fig, axes = plt.subplots(len(names), 2, figsize=(12, 2.2 * len(names)), squeeze=False)
    t = validation.t
    for i, name in enumerate(names):
        y = validation.targets[:, TARGET_NAMES.index(name)]
        info = TARGET_INFO[name]
        left, right = axes[i]
        left.plot(t, y, ".", ms=2, color="0.3", label="measured")
        left.plot(t, pred[:, i], "-", lw=1, color="C1", label="model")
        left.set_ylabel(f"{name} [{info['unit']}]")
        right.plot(t, y - pred[:, i], ".", ms=2, color="C3")
        right.axhline(0.0, color="0.5", lw=0.8)
        right.set_ylabel("residual")
        if i == 0:
            left.legend(loc="upper right", fontsize=8)
            left.set_title("validation rows: measured and model")
            right.set_title("measured - model")
    for ax in axes[-1]:
        ax.set_xlabel("log time [s]")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def write_model_report(
    model: Any,
    train: Dataset,
    validation: Dataset,
    out_dir: str | Path,
    checks: list[Check],
    title: str = "model report",
) -> tuple[Path, Path]:
    """Write report.md and fit.png into out_dir for a fitted model (QuadrotorModel); returns both paths."""
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"cannot create the report folder {out}: {exc.strerror}") from None
    if len(validation) == 0:
        raise UserError("the model report needs validation rows", hint="lower --holdout or give more data")
    png = _figure(model, validation, out / "fit.png")
    pred_v = model.predict(validation)
    pred_t = model.predict(train)
    lines = [f"# {title}", ""]
    lines.append(
        f"Data: {len(train)} training rows, {len(validation)} validation rows (the last part of each flight)."
    )
    for f in validation.flights:
        lines.append(f"- {f.file} ({f.format}, targets from {f.target_source})")
    if train.segments:
        lines += ["", "Flight segmentation:", "", "```", *train.segments, "```"]
    lines += [
        "",
        "| target | unit | train R^2 | validation R^2 | validation RMSE |",
        "| --- | --- | --- | --- | --- |",
    ]
    for i, name in enumerate(model.target_names):
        j = TARGET_NAMES.index(name)
        mt = table_metrics(train.targets[:, j], pred_t[:, i])
        mv = table_metrics(validation.targets[:, j], pred_v[:, i])
        lines.append(
            f"| {name} | {TARGET_INFO[name]['unit']} | {mt['r2']:.4f} | {mv['r2']:.4f} | {mv['rmse']:.4g} |"
        )
    lines += ["", f"## Equations (coefficients to {DIGITS} significant digits)", "", DISPLAY_LEGEND + ".", ""]
    for name, expr in model.equations.items():
        info = TARGET_INFO[name]
        lines.append(f"**{name}** ({info['description']}, {info['unit']}, {info['frame']}):")
        lines.append("")
        for group, text in equation_text(name, expr, DIGITS):
            lines.append(f"- {group}: `{text}`")
        lines.append("")
    flags = model_flags(model, validation)
    lines += ["## Plausibility", "", *(f"- {c.line()}" for c in checks), ""]
    lines += ["## Flags", ""] + ([f"- {f}" for f in flags] or ["- none"]) + [""]
    search = search_lines(getattr(getattr(model, "model_", None), "engine", {}) or {})
    if search:
        lines += ["## How the engine searched", "", *search, ""]
    lines += ["## Fit on the validation rows", "", f"![measured and model, residuals]({png.name})", ""]
    md = out / "report.md"
    md.write_text("\n".join(lines), encoding="utf-8")
    return md, png


def equations_block(model: Any, digits: int = DIGITS) -> str:
    """The equations as text lines grouped by physical meaning, for the terminal."""
    out = [f"equations (coefficients to {digits} significant digits; {DISPLAY_LEGEND}):"]
    for name, expr in model.equations.items():
        info = TARGET_INFO[name]
        out.append(f"  {name} [{info['unit']}, {info['frame']}] =")
        for group, text in equation_text(name, expr, digits):
            out.append(f"      {group:>12}: {text}")
    return "\n".join(out)
