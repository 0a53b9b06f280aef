"""report.md of `quadsr paper`, its CSV tables and combined figures, and the paper's equations.

The equations are shown in one normal form for the learned, the paper's and the true model alike (LaTeX via
sympy): expanded, rotor-speed sums regrouped into f1..f4 and Omega_r, body-axis drag regrouped into
v_b,i |v_b,i| (v_b = R^T v), coefficients rounded to 4 significant digits and factored out where they agree at
that precision. An expression that is not a polynomial in those building blocks is shown as sympy prints it.
"""

from __future__ import annotations

import csv
import functools
import hashlib
import math
import platform
import sys
from collections.abc import Sequence
from dataclasses import asdict
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import sympy

from identification.kinematics import euler_rate_matrix_sym, rotation_matrix_sym
from identification.model_file import SYMBOLS, TARGET_INFO, TARGET_NAMES, Model, parse_expression
from identification.paper_model import PAPER_KINEMATICS, PAPER_ZETA, paper_model
from identification.validate import PAPER_TABLE, comparison_markdown, table_markdown

if TYPE_CHECKING:
    from quadsr.pipeline import PaperRun, TrackingRow

SIGN_NOTES = """\
- Frames: the paper's earth frame has gravity along +Z_e and thrust along -Z_b, as our NED earth and FRD body
  frames, so x'', y'', z'' and wx', wy', wz' compare directly.
- Motor combinations: the paper's (u2^2+u3^2-u1^2-u4^2), (u1^2+u3^2-u2^2-u4^2), (u1^2+u2^2-u3^2-u4^2) are our
  f2, f3, f4 with the rotors in PX4 Quad-X order, so the torque terms keep their signs.
- Gyroscopic products: the paper has +0.697 wy wz, -0.708 wx wz, +0.0219 wx wy. Euler's equations with
  the paper's own inertias (Table II) give (Jyy-Jzz)/Jxx = -0.697, (Jzz-Jxx)/Jyy = +0.708,
  (Jxx-Jyy)/Jzz = -0.0219: all three of the paper's signs are flipped (w x Jw added instead of subtracted).
  The learned model finds Euler's signs.
- Our vehicle also has the rotor gyroscopic torque (Jm, from the BUAA simulator code: the Omega_r terms) and a
  small body-rate damping (the wx, wy, wz terms); the paper's equations have neither.
- Translation: the paper's zeta_4 and zeta_5 are fits near hover (u1 and u2 u4 standing in for f1, theta for
  sin(theta), sin(phi + psi) for the rotation), its zeta_6 has 9.44 for g = 9.8 and a drag -0.000289 vz^2
  that is right only when falling; the SITL (and the learned model) has the exact rotation of the thrust and
  quadratic drag along each body axis (v_b = R^T v)."""

# --------------------------------------------------------------------------------------------------------
# Display normal form


_AXES = "xyz"
_S = SYMBOLS
_R = rotation_matrix_sym(_S["phi"], _S["theta"], _S["psi"])
_VB = [sympy.expand(c) for c in _R.T * sympy.Matrix([_S["vx"], _S["vy"], _S["vz"]])]
_V = [sympy.Symbol(f"v_b{a}") for a in _AXES]  # body velocity component, display only
_A = [sympy.Symbol(f"v_b{a}_abs") for a in _AXES]  # its absolute value, display only
_TRIG = [f(_S[n]) for n in ("phi", "theta", "psi") for f in (sympy.sin, sympy.cos)]
_TV = [_S["vx"], _S["vy"], _S["vz"], *_TRIG]  # what the drag quotient and rotation factors are made of
_U = [_S[f"u{i}"] for i in range(1, 5)]
_OTHER = [_S[n] for n in ("wx", "wy", "wz", "x", "y", "z", "phi", "theta", "psi")]
# motor combinations (docs/design.md): name -> (power of u_i, sign per rotor)
_COMBINATIONS = {
    "f1": (2, (1, 1, 1, 1)), "f2": (2, (-1, 1, 1, -1)), "f3": (2, (1, -1, 1, -1)), "f4": (2, (1, 1, -1, -1)),
    "Omega_r": (1, (-1, -1, 1, 1)),
}
_F = {name: sympy.Symbol(name) for name in _COMBINATIONS}
LATEX_NAMES: dict[sympy.Symbol, str] = {
    **{_V[i]: f"v_{{b,{a}}}" for i, a in enumerate(_AXES)},
    **{_A[i]: rf"\lvert v_{{b,{a}}} \rvert" for i, a in enumerate(_AXES)},
    **{_F[f"f{i}"]: f"f_{i}" for i in range(1, 5)},
    _F["Omega_r"]: r"\Omega_r",
    **{_S[f"v{a}"]: f"v_{a}" for a in _AXES},
    **{_S[f"w{a}"]: rf"\omega_{a}" for a in _AXES},
    **{_S[f"u{i}"]: f"u_{i}" for i in range(1, 5)},
}
TARGET_LATEX = {"ax": r"\ddot x", "ay": r"\ddot y", "az": r"\ddot z", "dwx": r"\dot\omega_x",
                "dwy": r"\dot\omega_y", "dwz": r"\dot\omega_z"}
SIGNIFICANT = 4


def _rounded(value: float) -> float:
    return float(f"{value:.{SIGNIFICANT}g}")


def _abs_to_symbol(node: sympy.Expr) -> sympy.Expr:
    arg = node.args[0]
    for i, vb in enumerate(_VB):
        if sympy.expand(arg - vb) == 0 or sympy.expand(arg + vb) == 0:
            return _A[i]
    return node


def _monomial(gens: Sequence[sympy.Expr], exponents: Sequence[int], which: Sequence[int]) -> sympy.Expr:
    return sympy.Mul(*[gens[k] ** exponents[k] for k in which if exponents[k]])


@functools.lru_cache(maxsize=128)
def display_terms(expr: sympy.Expr) -> tuple[tuple[float, sympy.Expr], ...] | None:
    """The expression as (coefficient, factor) terms in the display normal form; None if it has none."""
    e = sympy.expand(expr).replace(lambda n: isinstance(n, sympy.Abs), _abs_to_symbol)
    gens: list[sympy.Expr] = [*_A, *_U, *_TV, *_OTHER]
    gens += sorted((a for a in e.atoms(sympy.Function, sympy.Symbol) if a not in gens),
                   key=sympy.default_sort_key)
    try:
        poly = sympy.Poly(e, *gens)
    except sympy.PolynomialError:
        return None
    iu = [gens.index(u) for u in _U]
    itv = [gens.index(g) for g in _TV]
    iother = [k for k in range(len(gens)) if k not in iu and k not in itv]
    by_rest: dict[tuple[int, ...], dict[tuple[int, ...], float]] = {}
    for monom, coef in poly.terms():
        rest = tuple(0 if k in iu else p for k, p in enumerate(monom))
        by_rest.setdefault(rest, {})[tuple(monom[k] for k in iu)] = float(coef)
    # 1. rotor speeds: four u_i^p terms with one coefficient and a combination's signs -> that combination
    items: list[tuple[float, sympy.Expr, sympy.Expr]] = []  # (coefficient, key factor, trig/velocity part)
    for rest, by_u in by_rest.items():
        key, tv = _monomial(gens, rest, iother), _monomial(gens, rest, itv)
        for name, (power, signs) in _COMBINATIONS.items():
            ks = [tuple(power if j == i else 0 for j in range(4)) for i in range(4)]
            if all(k in by_u for k in ks):
                members = [by_u[k] * s for k, s in zip(ks, signs, strict=True)]
                if len({_rounded(c) for c in members}) == 1:
                    items.append((sum(members) / 4, _F[name] * key, tv))
                    for k in ks:
                        del by_u[k]
        for um, c in by_u.items():
            items.append((c, sympy.Mul(*[u**p for u, p in zip(_U, um, strict=True)]) * key, tv))
    # 2. per key factor, the trig/velocity polynomial; with |v_b,i| in the key, divided by v_b,i if it can be
    groups: dict[sympy.Expr, sympy.Expr] = {}
    for c, key, tv in items:
        groups[key] = groups.get(key, sympy.Integer(0)) + sympy.Float(c) * tv
    out: list[tuple[float, sympy.Expr]] = []
    for key, q in groups.items():
        extra: sympy.Expr = sympy.Integer(1)
        for i in range(3):
            if key.has(_A[i]):
                quotient, remainder = sympy.div(q, _VB[i], *_TV)
                scale = max(abs(float(c)) for c in sympy.Poly(q, *_TV).coeffs())
                rest = sympy.Poly(remainder, *_TV)
                if rest.is_zero or max(abs(float(c)) for c in rest.coeffs()) <= 1e-9 * scale:
                    q, extra = quotient, _V[i]
                break
        terms = [(m, float(c)) for m, c in sympy.Poly(q, *_TV).terms() if float(c) != 0.0]
        if not terms:
            continue
        parts = [(sympy.Mul(*[g**p for g, p in zip(_TV, m, strict=True)]), c) for m, c in terms]
        if len({_rounded(abs(c)) for _, c in parts}) == 1:
            first = parts[0][1]
            norm = sympy.Add(*[(1 if c * first > 0 else -1) * mono for mono, c in parts])
            out.append((math.copysign(sum(abs(c) for _, c in parts) / len(parts), first), norm * extra * key))
        else:
            out += [(c, mono * extra * key) for mono, c in parts]

    def order(term: tuple[float, sympy.Expr]) -> int:
        f = term[1]
        if f.has(*_F.values()):
            return 0
        if f.has(*_A):
            return 1
        return 3 if f == 1 else 2

    return tuple(sorted(out, key=order))


def latex_number(value: float) -> str:
    """A number to 4 significant digits in LaTeX (scientific as a \\cdot 10^{b} outside 1e-3..1e4)."""
    if value == 0 or not math.isfinite(value):
        return str(value)
    mantissa, exponent = f"{value:.{SIGNIFICANT - 1}e}".split("e")
    if -3 <= int(exponent) < 4:
        return f"{value:.{SIGNIFICANT}g}"
    return rf"{float(mantissa):.{SIGNIFICANT}g} \cdot 10^{{{int(exponent)}}}"


@functools.lru_cache(maxsize=128)
def equation_latex(expr: sympy.Expr) -> str:
    """The right-hand side in LaTeX, in the display normal form with rounded coefficients."""
    terms = display_terms(expr)
    if terms is None:
        floats = expr.atoms(sympy.Float)
        rounded = expr.xreplace({f: sympy.Float(_rounded(float(f)), SIGNIFICANT) for f in floats})
        return sympy.latex(rounded, symbol_names=LATEX_NAMES, fold_func_brackets=True)
    if not terms:
        return "0"
    parts = []
    for c, factor in terms:
        body = latex_number(abs(c))
        if factor != 1:
            body += " " + sympy.latex(factor, symbol_names=LATEX_NAMES, fold_func_brackets=True)
        parts.append(("- " if c < 0 else "+ ") + body)
    text = " ".join(parts)
    return text[2:] if text.startswith("+ ") else text


@functools.lru_cache(maxsize=1)
def kinematics_match_paper() -> bool:
    """True when our known Euler-angle rates equal the paper's zeta_7..9 identically."""
    ours = euler_rate_matrix_sym(_S["phi"], _S["theta"]) * sympy.Matrix([_S["wx"], _S["wy"], _S["wz"]])
    theirs = [parse_expression(PAPER_KINEMATICS[k]) for k in ("dphi", "dtheta", "dpsi")]
    return all(sympy.simplify(a - b) == 0 for a, b in zip(ours, theirs, strict=True))


def expressions_fingerprint(model: Model) -> str:
    """SHA-256 (first 16 hex digits) of the six expression strings: equal for equal learned equations."""
    from identification.model_file import expression_to_string

    text = "\n".join(f"{n}={expression_to_string(model.targets[n].expression)}" for n in model.target_names)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


# --------------------------------------------------------------------------------------------------------
# CSV tables


def write_identification_csv(metrics: dict[str, dict[str, float]], path: Path) -> Path:
    """Table I as CSV: per target our RMSE, MAE, R^2 (validation flight) beside the paper's."""
    with path.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["target", "unit", "rmse", "mae", "r2", "rows", "paper_rmse", "paper_mae", "paper_r2"])
        for name, m in metrics.items():
            p = PAPER_TABLE[name]
            w.writerow([name, TARGET_INFO[name]["unit"], repr(m["rmse"]), repr(m["mae"]), repr(m["r2"]),
                        m.get("rows", ""), p["rmse"], p["mae"], p["r2"]])
    return path


_METRIC_FIELDS = ("duration_s", "samples", "completed", "crashed", "rms_m", "rms_after_5s_m", "max_m",
                  "final_m", "settle_time_s", "yaw_rms_rad", "yaw_max_rad", "motor_limit_share",
                  "max_tilt_deg", "step_median_us", "step_p99_us")


def write_tracking_csv(rows: Sequence[TrackingRow], path: Path) -> Path:
    """One CSV row per tracking flight: controller, case, state source, every metric (SI units), message."""
    with path.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["controller", "case", "state", *_METRIC_FIELDS, "message", "flight_dir"])
        for r in rows:
            values = asdict(r.metrics) if r.metrics is not None else {}
            w.writerow([r.label, r.case, r.state, *["" if values.get(k) is None else values[k]
                                                    for k in _METRIC_FIELDS],
                        r.message, "" if r.flight_dir is None else r.flight_dir.name])
        fh.flush()
    return path


# --------------------------------------------------------------------------------------------------------
# Markdown tables


def millimetres(v: float | None) -> str:
    """A length in m as millimetres: 2 decimals, or 2 significant digits below 0.1 mm ('-' for None)."""
    if v is None:
        return "-"
    mm = v * 1000
    return f"{mm:.2f}" if mm == 0 or abs(mm) >= 0.1 or not math.isfinite(mm) else f"{mm:.1e}"


def tracking_markdown(rows: Sequence[TrackingRow], state_column: bool = False,
                      link_base: Path | None = None) -> str:
    """The tracking table: every controller and case; link_base: link each flight's figures relative to it."""
    head = ["controller", "case"] + (["state"] if state_column else []) + [
        "RMS [mm]", "RMS after 5 s [mm]", "max [mm]", "final [mm]", "settle 5 cm [s]", "yaw RMS [rad]",
        "yaw max [rad]", "motor limits", "step median [us]", "step p99 [us]", "completed"]
    if link_base is not None:
        head.append("figures")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        cells = [r.label, r.case] + ([r.state] if state_column else [])
        m = r.metrics
        if m is None:
            cells += ["no data: " + r.message.replace("\n", " ")] + ["-"] * (len(head) - len(cells) - 1)
            lines.append("| " + " | ".join(cells) + " |")
            continue
        settle = "never" if m.settle_time_s is None else f"{m.settle_time_s:.2f}"
        done = "yes" if m.completed and not m.crashed else f"NO ({r.message})"
        cells += [*map(millimetres, (m.rms_m, m.rms_after_5s_m, m.max_m, m.final_m)), settle,
                  f"{m.yaw_rms_rad:.2e}", f"{m.yaw_max_rad:.2e}", f"{m.motor_limit_share:.1%}",
                  f"{m.step_median_us:.0f}", f"{m.step_p99_us:.0f}", done]
        if link_base is not None:
            d = r.flight_dir
            cells.append("-" if d is None else f"[x,y,z,psi]({_rel(d / 'tracking.png', link_base)}) "
                                               f"[3-D]({_rel(d / 'path3d.png', link_base)})")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _rel(path: Path, base: Path) -> str:
    try:
        return path.resolve().relative_to(base.resolve()).as_posix()
    except ValueError:
        return path.as_posix()


# --------------------------------------------------------------------------------------------------------
# Figures (PNG, Agg)


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
    from quadsr.pipeline import LEARNED_LABEL

    # the learned-model line is drawn wide and light so the true-model line on top of it stays visible
    return {"lw": 3.0, "alpha": 0.45} if label == LEARNED_LABEL else {"lw": 1.1}


def tracking_overlay_figure(rows: Sequence[TrackingRow], case: str, path: Path) -> Path:
    """Figs. 4 and 6: x, y, z [m, NED] and psi [rad] over t [s], desired and every controller on one case."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(4, 1, figsize=(8.0, 9.5), sharex=True)
    names = (("ref_x", "true_x", "x [m]"), ("ref_y", "true_y", "y [m]"),
             ("ref_z", "true_z", "z [m] (NED, down)"), ("ref_yaw", "true_psi", "psi [rad]"))
    desired_drawn = False
    for r in rows:
        if r.case != case:
            continue
        d = _steps(r)
        if d is None:
            continue
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
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cases = sorted({r.case for r in rows})
    fig = plt.figure(figsize=(6.5 * max(len(cases), 1), 6.0))
    for k, case in enumerate(cases, 1):
        ax = fig.add_subplot(1, len(cases), k, projection="3d")
        desired_drawn = False
        for r in rows:
            if r.case != case:
                continue
            d = _steps(r)
            if d is None:
                continue
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


# --------------------------------------------------------------------------------------------------------
# report.md


def versions() -> dict[str, str]:
    """Versions of python and the packages the results depend on."""
    out = {"python": platform.python_version()}
    for name in ("quadsr", "numpy", "sympy", "pymavlink", "pyoperon"):
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = "not installed"
    return out


def checks(run: PaperRun) -> list[tuple[str, bool | None]]:
    """The issue's floors on this run: (what, passed; None when the stage did not run)."""
    from quadsr.pipeline import CASES, LEARNED_LABEL, TRUE_LABEL

    out: list[tuple[str, bool | None]] = []
    v = run.validation
    out.append(("learned model: R^2 >= 0.999 on every target on the validation flight",
                None if v is None else all(v.metrics[t]["r2"] >= 0.999 for t in TARGET_NAMES)))
    out.append(("learned model: the true model's terms and no others, on every target",
                None if v is None or v.comparisons is None else all(c.same_terms for c in v.comparisons)))
    by = {(r.label, r.case): r.metrics for r in run.tracking}
    for case in CASES:
        m = by.get((LEARNED_LABEL, case))
        ok = None if run.stage("track").status != "done" else \
            bool(m is not None and m.rms_after_5s_m is not None and m.rms_after_5s_m < 0.01 and m.completed)
        out.append((f"backstepping on the learned model, {case}: RMS after 5 s < 1 cm", ok))
        ref = by.get((TRUE_LABEL, case))
        ratio_ok = ok
        if ok:
            ratio_ok = bool(ref is not None and ref.rms_after_5s_m
                            and m.rms_after_5s_m <= 1.2 * ref.rms_after_5s_m)
        out.append((f"backstepping on the learned model, {case}: RMS after 5 s <= 1.2 x the true-model "
                    "controller's", ratio_ok))
        out.append((f"backstepping on the learned model, {case}: median control step < 200 us",
                    None if ok is None else bool(m is not None and m.step_median_us < 200.0)))
    m = by.get((LEARNED_LABEL, "case2"))
    out.append(("backstepping on the learned model, case2: within 5 cm of the reference by 4 s",
                None if run.stage("track").status != "done" else
                bool(m is not None and m.settle_time_s is not None and m.settle_time_s <= 4.0)))
    return out


def _status_line(run: PaperRun) -> str:
    if run.finished:
        return (f"**Complete**: every stage ran; {run.total_wall_s:.1f} s in the stages, "
                f"{run.elapsed_s:.1f} s wall in all.")
    if run.failure:
        return f"**Incomplete: {run.failure}.** The sections below hold what completed before it."
    return "**In progress**: the sections below hold what has completed so far."


def _not_yet(run: PaperRun, stage: str) -> str:
    return f"_Not available: stage '{stage}' {run.stage(stage).status}._\n"


def _equations_section(run: PaperRun) -> list[str]:
    lines = ["## Learned equations beside the paper's and the true model", "",
             "Notation: $f_1 = u_1^2+u_2^2+u_3^2+u_4^2$, $f_2 = -u_1^2+u_2^2+u_3^2-u_4^2$, "
             "$f_3 = u_1^2-u_2^2+u_3^2-u_4^2$, $f_4 = u_1^2+u_2^2-u_3^2-u_4^2$ (rad²/s²), "
             r"$\Omega_r = -u_1-u_2+u_3+u_4$ (rad/s), $v_b = R^\top v$ the velocity in body axes (m/s), "
             r"$R = R_z(\psi) R_y(\theta) R_x(\phi)$. Earth NED, body FRD. Coefficients rounded to 4 "
             "significant digits (the model files hold them exactly).", "",
             "Paper to ours: " + r"$\xi_4..\xi_6 = v_x, v_y, v_z$; $\xi_7..\xi_9 = \phi, \theta, \psi$; "
             r"$\xi_{10}..\xi_{12} = \omega_x, \omega_y, \omega_z$.", "",
             "Sign conventions and differences:", "", SIGN_NOTES, ""]
    paper = paper_model()
    for name in TARGET_NAMES:
        lhs = TARGET_LATEX[name]
        lines += [f"### {TARGET_INFO[name]['description']} ({name}; paper ζ{PAPER_ZETA[name]})", ""]
        if run.model is not None and name in run.model.targets:
            r2 = "" if run.validation is None else \
                f", R² {run.validation.metrics[name]['r2']:.6f} on the validation flight"
            lines += [f"Ours (learned{r2}):", "", "$$",
                      f"{lhs} = {equation_latex(run.model.expressions[name])}", "$$", ""]
        lines += [f"Paper (ζ{PAPER_ZETA[name]}):", "", "$$",
                  f"{lhs} = {equation_latex(paper.expressions[name])}", "$$", ""]
        if run.truth is not None:
            lines += ["True model (the SITL's equations, from the vehicle file):", "", "$$",
                      f"{lhs} = {equation_latex(run.truth.expressions[name])}", "$$", ""]
    same = "identical to" if kinematics_match_paper() else "DIFFERENT from"
    lines += ["### Euler-angle rates (paper ζ7..ζ9: known transforms, not learned)", "",
              f"Our kinematics (identification.kinematics) are {same} the paper's:", "", "$$",
              r"\dot\phi = \omega_x + \tan\theta\,(\sin\phi\,\omega_y + \cos\phi\,\omega_z),\quad "
              r"\dot\theta = \cos\phi\,\omega_y - \sin\phi\,\omega_z,\quad "
              r"\dot\psi = \frac{\sin\phi\,\omega_y + \cos\phi\,\omega_z}{\cos\theta}", "$$", ""]
    return lines


def _paper_terms_table(run: PaperRun) -> list[str]:
    if run.truth is None:
        return []
    lines = ["### Terms the paper's equations share with the true model", "",
             "Grouped as in the equations above; a sign that differs from the true model's is marked.", "",
             "| target | term | paper | true model | ours (learned) | paper's sign |",
             "|---|---|---|---|---|---|"]
    paper = paper_model()
    for name in TARGET_NAMES:
        truth = run.truth.expressions[name]
        ours = {}
        if run.model is not None and name in run.model.targets:
            ours = {f: c for f, _, c in display_comparison(run.model.expressions[name], truth)}
        for factor, true, theirs in display_comparison(paper.expressions[name], truth):
            if true is None or theirs is None:
                continue
            mine = ours.get(factor)
            sign = "same" if (theirs > 0) == (true > 0) else "**flipped**"
            lines.append(f"| {name} | ${factor}$ | {theirs:.4g} | {true:.4g} | "
                         f"{'-' if mine is None else f'{mine:.4g}'} | {sign} |")
    return lines + [""]


def display_comparison(learned: sympy.Expr, reference: sympy.Expr) -> list[tuple[str, float | None,
                                                                              float | None]]:
    """Terms of two expressions in the display normal form: (LaTeX factor, reference coef, learned coef)."""
    got, ref = display_terms(learned), display_terms(reference)
    if got is None or ref is None:
        return []
    got_by = {f: c for c, f in got}
    rows = [(f, c, got_by.pop(f, None)) for c, f in ref] + [(f, None, c) for f, c in got_by.items()]
    return [("1" if f == 1 else sympy.latex(f, symbol_names=LATEX_NAMES, fold_func_brackets=True), r, g)
            for f, r, g in rows]


def _term_details(run: PaperRun) -> list[str]:
    lines = ["Term by term, grouped as in the equations above (a grouped term's coefficient is the mean of "
             "its members, which agree to 4 significant digits; per expanded monomial: "
             f"[validation/compare.csv]({_rel(run.validation.compare_csv, run.out)})):", "",
             "| target | term | true model | learned | rel. error | status |", "|---|---|---|---|---|---|"]
    for name in run.model.target_names:
        for factor, ref, got in display_comparison(run.model.expressions[name], run.truth.expressions[name]):
            err = "-" if ref is None or got is None else f"{abs(got - ref) / abs(ref):.2e}"
            status = "both" if ref is not None and got is not None else "extra" if ref is None else "missing"
            lines.append(f"| {name} | ${factor}$ | {'-' if ref is None else f'{ref:.6g}'} | "
                         f"{'-' if got is None else f'{got:.6g}'} | {err} | {status} |")
    return lines + [""]


def _link(run: PaperRun, key: str, text: str) -> str:
    path = run.files.get(key)
    return f"[{text}]({_rel(path, run.out)})" if path else text


def report_markdown(run: PaperRun) -> str:
    """report.md's text for the run as far as it got."""
    s = run.settings
    lines = ["# quadsr paper: Fang & Chen's identification and tracking, reproduced against the SITL", "",
             _status_line(run), "",
             f"- command: `{run.command}`",
             f"- seed: {run.seed} (excitation draws, SR engine, SITL)",
             f"- {s.describe()}",
             f"- vehicle: {run.vehicle.name} ({run.vehicle.source_path})",
             f"- started: {run.started_utc}", ""]
    if run.model is not None:
        lines += [f"- learned expressions fingerprint: `{expressions_fingerprint(run.model)}` "
                  "(SHA-256 of the six expressions; equal seeds give equal fingerprints)", ""]
    lines += ["## Stages", "", "| # | stage | what | status | wall time [s] | result |",
              "|---|---|---|---|---|---|"]
    for i, st in enumerate(run.stages, 1):
        wall = "-" if st.wall_s is None else f"{st.wall_s:.1f}"
        status = f"**{st.status}**" if st.status in ("failed", "interrupted") else st.status
        note = st.note.replace("|", "\\|").replace("\n", " ")
        lines.append(f"| {i} | {st.name} | {st.title} | {status} | {wall} | {note} |")
    lines += [f"| | total | | | {run.total_wall_s:.1f} | |", ""]

    lines += ["## Identification: Table I (testing errors on the validation flight)", ""]
    if run.validation is not None:
        rows_train, rows_val = run.rows.get("train", "?"), run.rows.get("validate", "?")
        lines += [f"Model learned from paper-train ({rows_train} rows, the last 20 % held out for the pick), "
                  f"evaluated on paper-validate ({rows_val} rows, the paper's sinusoids). Ours beside the "
                  "paper's Table I:", "", table_markdown(run.validation.metrics, paper=True),
                  f"CSV: {_link(run, 'identification_csv', 'identification.csv')}. "
                  f"Model: {_link(run, 'model', 'model.yaml')}; true model: "
                  f"{_link(run, 'true_model', 'true-model.yaml')}.", "",
                  f"![Fig. 3: the validation flight's targets, true against model]"
                  f"({_rel(run.files['fig3'], run.out)})", ""]
    else:
        lines.append(_not_yet(run, "validate"))
    lines += _equations_section(run)

    lines += ["## Term comparison: learned against the true model", ""]
    if run.validation is not None and run.validation.comparisons is not None:
        lines += ["Per expanded monomial (same terms: the same monomials with a nonzero coefficient):", "",
                  comparison_markdown(run.validation.comparisons), *_term_details(run)]
    else:
        lines.append(_not_yet(run, "validate"))
    lines += _paper_terms_table(run)

    lines += ["## Tracking: Case I and Case II", ""]
    if run.tracking:
        lines += [f"Each flight {s.track_duration:g} s from the ground at the origin, against its own SITL "
                  "child (lockstep, ideal sensors), the true state fed back. Errors are 3-D position errors; "
                  "'RMS after 5 s' leaves out the take-off from 3.7 m (Case I) and 4.5 m (Case II) away.", "",
                  tracking_markdown(run.tracking, link_base=run.out),
                  f"CSV: {_link(run, 'tracking_csv', 'tracking.csv')}.", ""]
        laws = {r.label: r.law for r in run.tracking if r.law}
        if laws:
            lines += ["How each model-based controller was built:", ""]
            lines += [f"- {label}: {law}" for label, law in laws.items()] + [""]
    else:
        lines.append(_not_yet(run, "track"))
    if "fig4" in run.files:
        lines += [f"![Fig. 4: Case I]({_rel(run.files['fig4'], run.out)})", "",
                  f"![Fig. 5: 3-D paths]({_rel(run.files['fig5'], run.out)})", "",
                  f"![Fig. 6: Case II]({_rel(run.files['fig6'], run.out)})", ""]
    else:
        lines.append(_not_yet(run, "figures"))

    lines += ["## Checks", ""]
    for what, ok in checks(run):
        lines.append(f"- {'PASS' if ok else 'not run' if ok is None else 'FAIL'}: {what}")
    lines += ["", "## Files", ""]
    tlogs = [run.files[k] for k in sorted(run.files) if k.startswith("tlog_")]
    tlogs += [r.flight_dir / "flight.tlog" for r in run.tracking
              if r.flight_dir is not None and (r.flight_dir / "flight.tlog").is_file()]
    lines += [f"- {_link(run, k, run.files[k].name)}" for k in ("model", "true_model", "identification_csv",
                                                                  "tracking_csv") if k in run.files]
    lines += [f"- [{_rel(p, run.out)}]({_rel(p, run.out)})" for p in tlogs]
    lines += ["", "## Versions", "", "| | version |", "|---|---|"]
    lines += [f"| {k} | {v} |" for k, v in versions().items()]
    lines += [f"| platform | {platform.platform()}, {sys.implementation.name} |", ""]
    return "\n".join(lines)


def write_report(run: PaperRun) -> Path:
    """Write DIR/report.md for the run as far as it got (atomically: a reader never sees half a file)."""
    path = run.out / "report.md"
    tmp = path.with_suffix(".md.tmp")
    tmp.write_text(report_markdown(run), encoding="utf-8")
    tmp.replace(path)
    return path

