"""report.md of `quadsr paper` and its CSV tables (equations: quadsr.equations; figures: quadsr.figures)."""

from __future__ import annotations

import csv
import hashlib
import math
import platform
import sys
from collections.abc import Sequence
from dataclasses import asdict
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING

from identification.equation_form import TARGET_LATEX, display_comparison, equation_latex
from identification.model_file import TARGET_INFO, TARGET_NAMES, Model
from identification.paper_model import PAPER_ZETA, paper_model
from identification.validate import PAPER_TABLE, comparison_markdown, table_markdown
from quadsr.equations import SIGN_NOTES, kinematics_match_paper

if TYPE_CHECKING:
    from quadsr.paper_run import PaperRun, TrackingRow


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
    from quadsr.paper_run import CASES, LEARNED_LABEL, TRUE_LABEL

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

