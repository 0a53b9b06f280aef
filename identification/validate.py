"""Model validation: the paper's Table I (RMSE, MAE, R^2 per target), Fig. 3 (targets true vs model over
time) and the comparison of each expression with a reference model (same terms, coefficient errors).

Terms: an expression is expanded into a sum of coefficient x monomial (sympy's expand, so f2 = -u1^2 + ...
gives four terms and Abs(...) arguments are expanded too); two models have the same terms when the sets of
monomials with a nonzero coefficient are equal.
"""

from __future__ import annotations

import csv
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import sympy

from identification.metrics import table_metrics, weak_metrics
from identification.model_file import TARGET_INFO, Model, expression_to_string
from identification.weak_form import WeakSettings, weak_rows

# The paper's Table I (testing errors of its SR model), for side-by-side printing.
PAPER_TABLE: dict[str, dict[str, float]] = {
    "ax": {"rmse": 0.2632, "mae": 0.2053, "r2": 0.9707},
    "ay": {"rmse": 1.2655, "mae": 0.8021, "r2": 0.8781},
    "az": {"rmse": 0.4011, "mae": 0.2745, "r2": 0.9907},
    "dwx": {"rmse": 0.0034, "mae": 0.0028, "r2": 1.0000},
    "dwy": {"rmse": 0.0013, "mae": 0.0011, "r2": 1.0000},
    "dwz": {"rmse": 6.7079e-5, "mae": 5.7108e-5, "r2": 1.0000},
}
_LATEX = {"ax": "x''", "ay": "y''", "az": "z''", "dwx": "wx'", "dwy": "wy'", "dwz": "wz'"}


def evaluate_model(
    model: Model, dataset: Any, weak: WeakSettings | None = None
) -> tuple[np.ndarray, dict[str, dict[str, float]]]:
    """Model predictions (N, n_targets) on a dataset's rows and Table I metrics per target.

    weak: the metrics in the weak form (identification.weak_form): targets and predictions both integrated
    against the test functions; `rows` then counts the weak rows.
    """
    pred = model.evaluate(dataset.xi, dataset.u)
    if pred.ndim == 1:
        pred = pred[None, :]
    metrics: dict[str, dict[str, float]] = {}
    names = ("ax", "ay", "az", "dwx", "dwy", "dwz")
    op = None if weak is None else weak_rows(dataset.t, getattr(dataset, "flight", None), weak)
    for j, name in enumerate(model.target_names):
        y = dataset.targets[:, names.index(name)]
        if op is not None:
            metrics[name] = weak_metrics(y, pred[:, j], op)
            metrics[name]["rows"] = int(op.shape[0])
            metrics[name]["nonfinite_predictions"] = int((~np.isfinite(pred[:, j])).sum())
            continue
        ok = np.isfinite(y) & np.isfinite(pred[:, j])
        metrics[name] = table_metrics(y[ok], pred[ok, j])
        metrics[name]["rows"] = int(ok.sum())
        metrics[name]["nonfinite_predictions"] = int((~np.isfinite(pred[:, j])).sum())
    return pred, metrics


def _fmt(v: float) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "nan"
    return f"{v:.4e}" if (v != 0 and abs(v) < 1e-3) else f"{v:.4f}"


def table_markdown(metrics: dict[str, dict[str, float]], paper: bool = False) -> str:
    """Table I as Markdown (with the paper's numbers beside when paper=True)."""
    head = "| Variable | RMSE | MAE | R^2 |"
    sep = "| --- | --- | --- | --- |"
    if paper:
        head += " paper RMSE | paper MAE | paper R^2 |"
        sep += " --- | --- | --- |"
    lines = [head, sep]
    for name, m in metrics.items():
        r2 = m["r2"]
        row = f"| {_LATEX.get(name, name)} ({name}) | {_fmt(m['rmse'])} | {_fmt(m['mae'])} | {r2:.6f} |"
        if paper:
            p = PAPER_TABLE[name]
            row += f" {_fmt(p['rmse'])} | {_fmt(p['mae'])} | {p['r2']:.4f} |"
        lines.append(row)
    return "\n".join(lines) + "\n"


def write_table(metrics: dict[str, dict[str, float]], out_dir: str | os.PathLike[str]) -> tuple[Path, Path]:
    """Write Table I as table1.md and table1.csv into out_dir; returns both paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    md = out / "table1.md"
    md.write_text(
        "# Testing errors of the model (paper Table I)\n\n" + table_markdown(metrics), encoding="utf-8"
    )
    csv_path = out / "table1.csv"
    with csv_path.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["target", "unit", "rmse", "mae", "r2", "rows"])
        for name, m in metrics.items():
            w.writerow(
                [
                    name,
                    TARGET_INFO[name]["unit"],
                    repr(m["rmse"]),
                    repr(m["mae"]),
                    repr(m["r2"]),
                    m.get("rows", ""),
                ]
            )
    return md, csv_path


def plot_traces(
    t: np.ndarray,
    truth: np.ndarray,
    model_pred: np.ndarray,
    names: tuple[str, ...],
    path: str | os.PathLike[str],
    flight: np.ndarray | None = None,
) -> Path:
    """Fig. 3: each target true vs model over time (s), one panel per target, PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    all_names = ("ax", "ay", "az", "dwx", "dwy", "dwz")
    n = len(names)
    rows = int(math.ceil(n / 2))
    fig, axes = plt.subplots(rows, 2 if n > 1 else 1, figsize=(11, 2.6 * rows), squeeze=False)
    t = np.asarray(t, float)
    breaks = np.zeros(len(t), bool)
    if flight is not None and len(t) > 1:
        breaks[1:] = np.diff(flight) != 0
    for k, name in enumerate(names):
        # targets of one kind in one column, as the paper's figure: linear left, angular right
        col = 0 if name in ("ax", "ay", "az") else 1
        row = ("ax", "ay", "az").index(name) if col == 0 else ("dwx", "dwy", "dwz").index(name)
        if n <= 2:
            row, col = 0, k
        ax = axes[min(row, rows - 1)][min(col, axes.shape[1] - 1)]
        y = truth[:, all_names.index(name)].astype(float).copy()
        p = model_pred[:, k].astype(float).copy()
        y[breaks] = np.nan
        p[breaks] = np.nan
        ax.plot(t, y, lw=1.2, color="tab:blue", label="actual system")
        ax.plot(t, p, lw=1.0, ls="--", color="tab:red", label="SR model")
        info = TARGET_INFO[name]
        ax.set_ylabel(f"{_LATEX[name]} ({info['unit']})")
        ax.grid(True, alpha=0.3)
        if k == 0:
            ax.legend(loc="upper right", fontsize=8)
    for a in axes[-1]:
        a.set_xlabel("t (s)")
    fig.suptitle("Comparison of the SR model with the actual system (paper Fig. 3)")
    fig.tight_layout()
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


# ---------------------------------------------------------------------------------------------------
# Reference comparison


def expression_terms(expr: sympy.Expr) -> dict[sympy.Expr, float]:
    """Expanded expression as {monomial: coefficient} (the constant term under key 1), zeros removed."""
    expanded = sympy.expand(expr)
    out: dict[sympy.Expr, float] = {}
    for term, coef in expanded.as_coefficients_dict().items():
        try:
            value = float(coef)
        except TypeError:
            continue
        if value != 0.0:
            out[term] = out.get(term, 0.0) + value
    return out


@dataclass
class TermRow:
    """One monomial of one target: its reference and learned coefficients."""

    target: str
    term: str
    reference: float | None
    learned: float | None

    @property
    def status(self) -> str:
        """'both', 'missing' (in the reference only) or 'extra' (in the learned model only)."""
        if self.reference is not None and self.learned is not None:
            return "both"
        return "missing" if self.learned is None else "extra"

    @property
    def relative_error(self) -> float | None:
        """|learned - reference| / |reference| for a term in both, else None."""
        if self.status != "both":
            return None
        return abs(self.learned - self.reference) / abs(self.reference)


@dataclass
class TargetComparison:
    """A learned target against the reference: same terms, the missing and extra ones, coefficient errors."""

    target: str
    rows: list[TermRow]

    @property
    def missing(self) -> list[str]:
        """Reference terms the learned expression lacks."""
        return [r.term for r in self.rows if r.status == "missing"]

    @property
    def extra(self) -> list[str]:
        """Learned terms the reference does not have."""
        return [r.term for r in self.rows if r.status == "extra"]

    @property
    def same_terms(self) -> bool:
        """True when both have exactly the same monomials."""
        return not self.missing and not self.extra

    @property
    def max_relative_error(self) -> float | None:
        """The largest coefficient relative error over the shared terms."""
        errs = [r.relative_error for r in self.rows if r.relative_error is not None]
        return max(errs) if errs else None


def compare_models(learned: Model, reference: Model) -> list[TargetComparison]:
    """Compare every target both models have, term by term."""
    return compare_expressions(
        {n: learned.targets[n].expression for n in learned.target_names},
        {n: t.expression for n, t in reference.targets.items()},
    )


def compare_expressions(
    learned: dict[str, sympy.Expr], reference: dict[str, sympy.Expr]
) -> list[TargetComparison]:
    """Compare every target both mappings have, monomial by monomial (any variable names: the 16 variables,
    or the body-frame primitives, where frame drag's |v| v is one monomial and not its NED expansion)."""
    out = []
    for name, expr in learned.items():
        if name not in reference:
            continue
        got = expression_terms(expr)
        ref = expression_terms(reference[name])
        keys = list(ref) + [k for k in got if k not in ref]
        rows = [TermRow(name, expression_to_string(k), ref.get(k), got.get(k)) for k in keys]
        out.append(TargetComparison(name, rows))
    return out


def _short(items: list[str], n: int = 4) -> str:
    if not items:
        return "-"
    shown = ", ".join(f"`{s}`" for s in items[:n])
    return shown + (f" (+{len(items) - n} more)" if len(items) > n else "")


def comparison_markdown(comparisons: list[TargetComparison]) -> str:
    """The per-target summary as Markdown."""
    lines = [
        "| target | same terms | terms (ref / learned) | missing | extra | max coefficient rel. error |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for c in comparisons:
        n_ref = sum(1 for r in c.rows if r.reference is not None)
        n_got = sum(1 for r in c.rows if r.learned is not None)
        err = c.max_relative_error
        lines.append(
            f"| {c.target} | {'yes' if c.same_terms else 'no'} | {n_ref} / {n_got} | {_short(c.missing)} | "
            f"{_short(c.extra)} | {'-' if err is None else f'{err:.3e}'} |"
        )
    return "\n".join(lines) + "\n"


def write_comparison(
    comparisons: list[TargetComparison], out_dir: str | os.PathLike[str]
) -> tuple[Path, Path]:
    """Write compare.md (summary, then each target's terms) and compare.csv (one row per term)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    md_lines = ["# Learned model against the reference\n", comparison_markdown(comparisons)]
    for c in comparisons:
        md_lines.append(
            f"\n## {c.target}\n\n| term | reference | learned | rel. error | status |\n"
            "| --- | --- | --- | --- | --- |"
        )
        for r in c.rows:
            ref = "-" if r.reference is None else f"{r.reference:.6g}"
            got = "-" if r.learned is None else f"{r.learned:.6g}"
            err = "-" if r.relative_error is None else f"{r.relative_error:.3e}"
            md_lines.append(f"| `{r.term}` | {ref} | {got} | {err} | {r.status} |")
    md = out / "compare.md"
    md.write_text("\n".join(md_lines) + "\n", encoding="utf-8")
    csv_path = out / "compare.csv"
    with csv_path.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["target", "term", "reference", "learned", "relative_error", "status"])
        for c in comparisons:
            for r in c.rows:
                w.writerow(
                    [
                        c.target,
                        r.term,
                        "" if r.reference is None else repr(r.reference),
                        "" if r.learned is None else repr(r.learned),
                        "" if r.relative_error is None else repr(r.relative_error),
                        r.status,
                    ]
                )
    return md, csv_path


@dataclass
class ValidationReport:
    """What `quadsr validate` wrote and found."""

    metrics: dict[str, dict[str, float]]
    table_md: Path
    table_csv: Path
    figure: Path
    comparisons: list[TargetComparison] | None = None
    compare_md: Path | None = None
    compare_csv: Path | None = None


def validate(
    model: Model,
    dataset: Any,
    out_dir: str | os.PathLike[str],
    reference: Model | None = None,
    weak: WeakSettings | None = None,
) -> ValidationReport:
    """Table I (md, csv), Fig. 3 (png) and, with a reference, the term comparison (md, csv) into out_dir.

    weak: Table I in the weak form (identification.weak_form); Fig. 3 still shows the point rows."""
    pred, metrics = evaluate_model(model, dataset, weak)
    md, csv_path = write_table(metrics, out_dir)
    fig = plot_traces(
        dataset.t,
        dataset.targets,
        pred,
        model.target_names,
        Path(out_dir) / "fig3_targets.png",
        flight=getattr(dataset, "flight", None),
    )
    report = ValidationReport(metrics, md, csv_path, fig)
    if reference is not None:
        report.comparisons = compare_models(model, reference)
        report.compare_md, report.compare_csv = write_comparison(report.comparisons, out_dir)
    return report
