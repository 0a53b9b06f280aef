"""From a dataset to a model: per target run the engine on the fit rows, build the Pareto front, pick on
the pick rows, report validation on rows used for neither (identification.data_roles), check how well the
flight identifies each chosen term (identification.collinearity) and flag targets below an R^2 threshold.

The physics-only candidates (identification.physics_candidates) join the engine's before the pick, every
candidate's self-feedback is measured (identification.self_feedback: anti-damping is set aside by the
pick), and a target the flight does not excite (identification.pareto.excited) gets the minimal physical
model with a flag (engine.flags, checks.not_excited).

With SelectionSettings.cv_folds > 1 the pick's evidence is blocked K-fold cross-validation over the fit and
pick rows together (identification.cross_validation: each candidate's terms refit without each fold and
the gap rows beside it), the pick is polished by one-term moves over every candidate's terms scored alike
(identification.cv_polish), and the chosen terms are refit on the fit and pick rows (identification.refit;
also alone with refit_with_pick_rows). The validation rows are in no fold.

Losses: 'absolute' (MAE, the paper's fitness) or 'squared' (RMSE), in the target's unit. The pick rule is
identification.pareto's. The budget is an iteration count (genetic-programming generations per target), so
the same data, settings and seed give the same model on any machine.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import sympy

from bridge.errors import UserError
from identification.body_frame import (
    BODY_TARGET_NAMES,
    STANDARD_GRAVITY,
    body_fit_names,
    body_targets,
    composed_targets,
    primitive_info,
)
from identification.candidate import Candidate
from identification.collinearity import (
    CONFOUNDER_VIF_LIMIT,
    VIF_LIMIT,
    Collinearity,
    column_collinearity,
    describe,
    forget_term_shapes,
    model_collinearity,
    term_shapes,
    terms_collinearity,
)
from identification.cross_validation import FoldedRows, attach_cross_validated, identify_on
from identification.cv_polish import move_candidate, new_shapes, polish_by_cross_validation, thrust_twins
from identification.data_roles import DEFAULT_GAP_S, assign_roles
from identification.dataset import Dataset
from identification.engine import ENGINE_NAMES, EngineSettings, make_engine
from identification.engine_settings import SelectionSettings
from identification.equation_form import equation_text
from identification.heap_reuse import reused_heap
from identification.height_law import body_values
from identification.law_refit import refit_law
from identification.library import build_library, feature_matrix
from identification.log_gravity import gravity_note
from identification.metrics import LOSSES, table_metrics, weak_metrics
from identification.model_file import TARGET_NAMES, BodyModel, Model, TargetModel, expression_to_string
from identification.pareto import admissible, attach_holdout, excited, front_points, select
from identification.physics_candidates import MINIMAL_TERMS, fit_terms, minimal_candidate, physics_candidates
from identification.refit import pool_screen, refit_rows, structure_test
from identification.self_feedback import mark_self_feedback
from identification.sparse import single_threaded_blas
from identification.specification_pick import specification_line, specification_pick
from identification.specification_search import SearchSpace, with_factors
from identification.supported_terms import supported_additions, supported_line
from identification.target_pool import frozen, map_targets, processes_for, thawed
from identification.weak_form import WeakSettings, overlap_lag, weak_rows
from identification.weak_noise import stacked_whitener, stated_whitener, uncertain_terms

DEFAULT_BUDGET = 60  # genetic-programming generations per target
R2_THRESHOLD = 0.9  # validation R^2 below this flags a target
# started first when targets are fitted side by side, the longest first: the thrust and roll/pitch moment
# targets hold the rotors' terms and, near the ground, the hub law (its variable projection and the rounds
# after it), and take two to four times the others' time (closed-loop fang-chen-aero: 26-36 s against 5-9 s
# per target). On two cores the third of them starts when one of the first two ends, so the two moments go
# first and the thrust third: the moments are the longest targets more often and by more (the heavy
# closed loop's wx' and wy' 84 and 74 s against fz's 39 s: the case took 125 s, fz then wx' on one worker,
# and simulated from those times 112 s with wy' then fz; closed-loop fang-chen-aero, where fz is longest,
# 56.6 -> 61.4 s); over the 28 case runs of seed 41 (session 67) the two workers' simulated wall summed
# 764 -> 757 s, and over the 39 of session 65 1643 -> 1619 s
LONGEST_FIRST = ("dwy", "dwx", "fz", "az")


def _polish_extra(eng: Any, current: list[sympy.Expr], folded: FoldedRows, selection: SelectionSettings,
                  before: list[sympy.Expr]) -> list[sympy.Expr]:
    """The terms the polish from the model `current` may use beside every candidate's (cv_polish: the
    engine's shape twins of its terms, the features most correlated with its cross-validated residual, its
    height terms times the rotors' thrust), after those of an earlier polish (`before`)."""
    twins = selection.cv_polish_twins
    extra = eng.nearest_features(current, twins) if twins > 0 and hasattr(eng, "nearest_features") else []
    if selection.cv_polish_residual > 0 and hasattr(eng, "residual_features"):
        extra += eng.residual_features([(part[0], part[2]) for part in folded.parts],
                                       folded.y - folded.predictions(current),
                                       selection.cv_polish_residual, [*current, *extra])
    if selection.cv_polish_thrust_twins:
        extra += [t for t in thrust_twins(current) if t not in extra]
    return [*before, *(t for t in extra if t not in before)]


def body_collinearity(expr: sympy.Expr, X: np.ndarray,
                      candidates: tuple[np.ndarray, Sequence[str]] | None = None) -> Collinearity:
    """Collinearity of a body-frame expression's terms on the rows X (N,16), the terms named in the
    body-frame primitives the engine learned them in (ub*Abs(ub), not their expansion in the 16 variables,
    which no reader can match to a term of the model); candidates as model_collinearity's."""
    shapes = [s for s in term_shapes(expr) if s != 1]
    cols = np.column_stack([body_values(s, X) for s in shapes]) if shapes else np.zeros((len(X), 0))
    return terms_collinearity(cols, [expression_to_string(s) for s in shapes], candidates)


def parse_targets(text: str | Sequence[str] | None) -> tuple[str, ...]:
    """'ax,dwx' (or a list) -> the targets in canonical order; UserError for unknown names."""
    if text is None:
        return TARGET_NAMES
    names = [t.strip() for t in text.split(",")] if isinstance(text, str) else [str(t).strip() for t in text]
    names = [n for n in names if n]
    bad = [n for n in names if n not in TARGET_NAMES]
    if bad or not names:
        raise UserError(
            f"unknown target {bad[0]!r}" if bad else "no targets given",
            hint=f"targets are {', '.join(TARGET_NAMES)} (comma-separated)",
        )
    return tuple(t for t in TARGET_NAMES if t in names)


class _Bar:
    """A tqdm bar per target on stderr (only on a terminal), throttled by tqdm's mininterval."""

    def __init__(self, target: str, enabled: bool):
        self.bar = None
        if enabled:
            from tqdm import tqdm

            self.bar = tqdm(
                total=1000,
                desc=f"{target:>4}",
                file=sys.stderr,
                leave=True,
                disable=None,  # None: off when stderr is not a terminal (CI logs)
                mininterval=0.2,
                bar_format="{desc} {percentage:3.0f}%|{bar}| {elapsed} {postfix}",
            )

    def __call__(self, fraction: float, status: str) -> None:
        if self.bar is not None:
            self.bar.set_postfix_str(status[:60], refresh=False)
            self.bar.update(int(1000 * min(max(fraction, 0.0), 1.0)) - self.bar.n)

    def close(self, status: str) -> None:
        if self.bar is not None:
            self.bar.set_postfix_str(status[:60], refresh=False)
            self.bar.update(1000 - self.bar.n)
            self.bar.close()


def _rows(d: Dataset) -> tuple[np.ndarray, np.ndarray]:
    """(X (N,16) = xi then u, targets (N,6)) of a dataset."""
    return np.hstack([d.xi, d.u]), d.targets


def identify(
    dataset: Dataset,
    *,
    engine: str = "default",
    targets: Sequence[str] = TARGET_NAMES,
    budget: int = DEFAULT_BUDGET,
    seed: int = 0,
    pick: Dataset | None = None,
    validate: Dataset | None = None,
    pick_fraction: float = 0.2,
    validate_fraction: float = 0.2,
    gap_s: float = DEFAULT_GAP_S,
    pick_blocks: int = 1,
    r2_threshold: float = R2_THRESHOLD,
    loss: str = "absolute",
    settings: EngineSettings | None = None,
    vehicle: dict[str, Any] | None = None,
    progress: bool = True,
    log: Callable[[str], None] | None = None,
    gravity: float = STANDARD_GRAVITY,
    weak: WeakSettings | None = None,
    jobs: int = 1,
) -> Model:
    """Identify the targets from a Dataset (identification.dataset); returns a learned Model.

    targets: of ax ay az dwx dwy dwz (a sequence, or one comma-separated string); UserError for any other
    name (the body-frame fx fy fz are learned for ax ay az, not asked for) or for none.
    budget: genetic-programming generations per target (an iteration count, not seconds). pick / validate:
    whole flights for those roles, else time blocks of each flight (pick_fraction, validate_fraction) with
    gap_s (s) between blocks; pick_blocks > 1: the pick rows in that many blocks spread over each flight
    (identification.data_roles.interleaved_masks). r2_threshold: a target whose validation R^2 is below it
    is flagged.
    An engine that learns in the body frame (frame "body", the default engine) fits fx fy fz dwx dwy dwz
    (identification.body_frame, with `gravity` in m/s^2) and the NED targets are composed from them.
    weak: fit, pick and report in the weak form (identification.weak_form): every loss and metric is on
    the rows integrated against the test functions (windows inside each role's rows); default engine only.
    jobs: targets fitted side by side in up to this many forked processes (identification.target_pool); the
    model is the same for any jobs, only the wall time changes.
    """
    if engine not in ENGINE_NAMES:
        raise UserError(f"unknown engine {engine!r}", hint=f"choose one of {', '.join(ENGINE_NAMES)}")
    if loss not in LOSSES:
        raise UserError(f"unknown loss {loss!r}", hint=f"choose one of {', '.join(LOSSES)}")
    if isinstance(budget, bool) or int(budget) != budget or budget < 1:
        raise UserError(f"the budget must be a whole number of generations >= 1 per target, got {budget}")
    if seed < 0:
        raise UserError(f"the seed must be >= 0, got {seed}")
    if isinstance(jobs, bool) or int(jobs) != jobs or jobs < 1:
        raise UserError(f"the number of processes (jobs) must be a whole number >= 1, got {jobs}")
    if not (np.isfinite(r2_threshold) and r2_threshold <= 1.0):
        raise UserError(f"the validation R^2 threshold must be a number <= 1, got {r2_threshold}")
    targets = parse_targets(targets)  # an unknown name (fx, a typo): an error, not an empty model
    settings = settings or EngineSettings()
    roles = assign_roles(
        dataset,
        pick=pick,
        validate=validate,
        pick_fraction=pick_fraction,
        validate_fraction=validate_fraction,
        gap_s=gap_s,
        pick_blocks=pick_blocks,
    )
    X, Y = _rows(roles.fit)
    Xp, Yp = _rows(roles.pick)
    Xv, Yv = _rows(roles.validate)
    body_frame = getattr(make_engine(engine, settings), "frame", "ned") == "body"
    if weak is not None:
        weak.check()
        if not hasattr(make_engine(engine, settings), "weak"):
            raise UserError(f"the weak form needs the default (discovery) engine, not {engine!r}",
                            hint="drop --weak or use --engine default")
    fit_names, Yf, Ypf, Yvf = tuple(targets), Y, Yp, Yv
    if body_frame:
        fit_names = body_fit_names(targets)
        Yf = body_targets(roles.fit.xi, Y, gravity)
        Ypf = body_targets(roles.pick.xi, Yp, gravity)
        Yvf = body_targets(roles.validate.xi, Yv, gravity)
    targets_done: dict[str, TargetModel] = {}
    wall: dict[str, dict[str, float]] = {}
    gates: dict[str, float] = {}
    identifiability: dict[str, Any] = {}
    below: dict[str, float] = {}
    not_excited: dict[str, dict[str, Any]] = {}
    evidence: dict[str, str] = {}  # per target: what the pick scored candidates on
    engine_stats: dict[str, dict[str, Any]] = {}  # per target: the engine's own account of its search
    warnings: list[str] = roles.notes()  # where the held-out blocks went when a flight's tail is steady
    engine_notes: list[str] = []
    total_start = time.perf_counter()
    library = build_library(settings.sparse.groups)
    library_names = [f.name for f in library]
    library_columns = feature_matrix(library, X)
    if body_frame:  # truth targets: a g other than the data's would be learned as drag or constant terms
        estimates = [e for d in (dataset, pick, validate) if d is not None for e in d.gravity_estimates]
        for file, g, se in estimates:
            note = gravity_note((g, se), gravity)
            if note is not None:
                warnings.append(f"warning: {file}: {note}")
    processes, serial_why = processes_for(jobs, len(fit_names))
    if serial_why:
        warnings.append(f"note: {len(fit_names)} targets fitted in {serial_why}")

    def fit_target(name: str) -> dict[str, Any]:
        """One target fitted, picked, polished, refit and checked (in a worker process when processes > 1)."""
        forget_term_shapes()  # the last target's candidates' shapes
        j = (BODY_TARGET_NAMES if body_frame else TARGET_NAMES).index(name)
        y, yp, yv = Yf[:, j], Ypf[:, j], Yvf[:, j]
        ok = np.all(np.isfinite(X), axis=1) & np.isfinite(y)
        okp = np.all(np.isfinite(Xp), axis=1) & np.isfinite(yp)
        okv = np.all(np.isfinite(Xv), axis=1) & np.isfinite(yv)
        eng = make_engine(engine, settings)
        ops = {"train": None, "pick": None, "validation": None}
        if weak is not None:
            ops = {
                "train": weak_rows(roles.fit.t[ok], roles.fit.flight[ok], weak),
                "pick": weak_rows(roles.pick.t[okp], roles.pick.flight[okp], weak),
                "validation": weak_rows(roles.validate.t[okv], roles.validate.flight[okv], weak),
            }
            eng.weak = (ops["train"], ops["pick"])
        noise = stated_whitener(roles.fit, ok, ops["train"], j) if settings.selection.stated_noise_t else None
        eng.noise = noise
        folded = None
        if settings.selection.cv_folds > 1:  # the pick's evidence: blocked K-fold CV over fit and pick rows
            folded = FoldedRows(
                [(X[ok], y[ok], ops["train"], _gap_rows(roles.fit.t[ok], ops["train"], gap_s)),
                 (Xp[okp], yp[okp], ops["pick"], _gap_rows(roles.pick.t[okp], ops["pick"], gap_s))],
                settings.selection.cv_folds, settings.selection.cv_blocks_per_fold, fit_noise=noise,
                all_noise=stacked_whitener(
                    [noise, stated_whitener(roles.pick, okp, ops["pick"], j)]) if noise is not None else None,
                identify_on_all=settings.selection.identify_on_pick_rows)
            if folded.usable and folded.identify_on_all and hasattr(eng, "identification"):
                eng.identification = folded.identification  # the engine's polish keeps what the pick would
        bar = _Bar(name, progress and processes == 1)
        start = time.perf_counter()
        try:
            candidates = eng.fit(X[ok], y[ok], name, int(budget), seed, loss, bar, (Xp[okp], yp[okp]))
        except BaseException:
            bar.close("failed")
            raise
        if not candidates:
            bar.close("no candidates")
            raise UserError(f"engine {engine} found no expression for {name}", hint="raise --budget")
        out: dict[str, Any] = {"engine_notes": list(getattr(eng, "notes", [])), "lines": []}
        lines = out["lines"]  # this target's warnings, after its engine notes
        candidates += physics_candidates(name, X[ok], y[ok], loss, ops["train"], noise)
        if folded is not None:
            if not folded.usable:
                line = (f"note: {name}: the fit and pick rows ({len(folded.y)}) are too few for "
                        f"{settings.selection.cv_folds}-fold cross-validation with {gap_s:g} s gaps beside "
                        "each held-out block; the pick rows alone pick")
                lines.append(line)
                out["evidence"] = "pick rows (too few rows for cross-validation)"
                folded = None
        if folded is not None:
            score = functools.partial(attach_cross_validated, rows=folded, kind=loss)
            if folded.identify_on_all:
                identify_on(candidates, folded)
            per_fold = folded.blocks // folded.folds
            out["evidence"] = (f"blocked {folded.folds}-fold cross-validation over the fit and pick rows "
                              f"({per_fold} block{'s' if per_fold > 1 else ''} per fold)")
        else:
            score = functools.partial(attach_holdout, X=Xp[okp], y=yp[okp], loss=loss, operator=ops["pick"])
        score(candidates)
        mark_self_feedback(candidates, X[ok], y[ok], name)
        pick_y = yp[okp] if ops["pick"] is None else ops["pick"] @ yp[okp]
        scale = folded.scale if folded is not None else float(np.std(pick_y)) if okp.any() else 1.0
        chosen = select(candidates, settings.selection, scale=scale, by_degree=True)
        extra: list[sympy.Expr] = []
        # the specification pick (below: weak rows, their noise covariance weighing the refit) chooses among
        # every candidate within the tolerance, not only the simplest: the polish keeps every move within it
        spec_pick = bool(settings.selection.specification_pick and settings.selection.refit_gls
                         and weak is not None)
        if folded is not None:  # one-term moves from the pick over every candidate's terms, scored alike
            mark = functools.partial(mark_self_feedback, X=X[ok], y=y[ok], target=name)
            start_from, sel = chosen, settings.selection
            for refits in range(sel.cv_polish_law_refits + 1):
                extra = _polish_extra(eng, term_shapes(start_from.expression), folded, sel, extra)
                picked = polish_by_cross_validation(start_from, candidates, folded, loss, sel, mark,
                                                    extra=extra, rounds=sel.cv_polish_rounds,
                                                    beam=sel.cv_polish_beam, all_tolerated=spec_pick)
                moved = set(term_shapes(picked.expression)) != set(term_shapes(chosen.expression))
                chosen = picked
                if refits == sel.cv_polish_law_refits or (refits and not moved):
                    break  # the refits done, or the last one's polish left the pick's terms as they were
                # the pick holding a ground-effect law: the law refit beside its terms, polished from there
                shapes = refit_law(term_shapes(chosen.expression), folded)
                start_from = None if shapes is None else move_candidate(
                    shapes, folded.terms_loss(shapes, loss), folded, loss, "law-refit")
                if start_from is None:
                    break
                mark([start_from])
                candidates.append(start_from)
        parts = [(X[ok], y[ok], ops["train"]), (Xp[okp], yp[okp], ops["pick"])]
        whiteners, spec = None, None
        if settings.selection.refit_gls and weak is not None:
            whiteners = [stated_whitener(part, mask, ops[key], j)
                         for part, mask, key in ((roles.fit, ok, "train"), (roles.pick, okp, "pick"))]
        if spec_pick:  # whiteners were made (refit_gls, weak rows)
            test = functools.partial(structure_test, parts=parts, whiteners=whiteners)
            space = None if folded is None else _search_space(candidates, extra, parts, whiteners, folded,
                                                               loss, settings.selection, X[ok], y[ok], name)
            chosen, spec = specification_pick(chosen, candidates, settings.selection, scale, test, space)
            if not any(c is chosen for c in candidates):
                candidates.append(chosen)
        flag = _excitation(name, candidates, (X[ok], y[ok]), loss, ops, settings, score)
        if flag is not None:
            chosen, line, out["not_excited"] = flag
            candidates.append(chosen)
            lines.append(f"warning: {line}")
        if settings.selection.refit_with_pick_rows or folded is not None:
            refit = refit_rows(chosen, parts, loss,
                               settings.sparse.irls_iterations, settings.sparse.irls_max_terms, whiteners)
            if refit is not None:
                candidates = [refit if c is chosen else c for c in candidates]
                chosen = refit
        supported = []  # terms the rows support beside the chosen ones, within the tolerance: named only
        if folded is not None and settings.selection.report_supported:
            supported = supported_additions(chosen, candidates, folded, loss, settings.selection.min_t, extra,
                                            settings.selection.report_supported)
        elapsed = time.perf_counter() - start
        splits = (("train", X, y, ok), ("pick", Xp, yp, okp), ("validation", Xv, yv, okv))
        # body frame: the values the NED targets' metrics are composed from (all of each split's rows), and
        # this target's own metrics on its finite rows of them (one evaluation per split)
        full = {split: chosen.evaluate(xx) for split, xx, _, _ in splits} if body_frame else None
        metrics = {}
        for split, xx, yy, mask in splits:
            pred = chosen.evaluate(xx[mask]) if full is None else full[split][mask]
            metrics[split] = (table_metrics(yy[mask], pred) if ops[split] is None
                              else weak_metrics(yy[mask], pred, ops[split]))
        if full is not None:
            out["predictions"] = full
        timings = {k: round(v, 3) for k, v in getattr(eng, "timings", {}).items()}
        timings["total"] = round(elapsed, 3)
        out["timings"] = timings
        if getattr(eng, "stats", None):  # what the engine did and why (e.g. discovery's hub_law: "none: ...")
            out["stats"] = dict(eng.stats)
        if getattr(eng, "gate_r2", None) is not None:
            out["gate"] = float(eng.gate_r2)
        if body_frame:  # the terms as functions of the 16 variables; the library's candidates are in the
            # body frame for the angular accelerations only (its forces are NED), so only they are tried there
            cands = (library_columns[ok], library_names) if name.startswith("dw") else None
            coll = body_collinearity(chosen.expression, X[ok], cands)
        else:
            coll = model_collinearity(chosen.expression, X[ok], (library_columns[ok], library_names))
        out["identifiability"] = coll.as_dict()
        # what the pick's t ratios (selection.min_t) took as each term's standard error
        out["identifiability"]["pick_t_ratios"] = (
            "under the log's stated noise of the weak rows" if noise is not None
            else "from the residual's effective sample size")
        # and on which rows (SelectionSettings.identify_on_pick_rows)
        out["identifiability"]["pick_t_rows"] = (
            "fit and pick rows" if folded is not None and folded.identify_on_all else "fit rows")
        lines += describe(name, coll)
        if spec is not None:  # the pick's structure rejected by the rows (specification_pick)
            out["identifiability"]["specification_pick"] = spec
            lines.append(specification_line(name, spec))
        if supported:
            out["identifiability"]["supported_additions"] = [f.as_dict() for f in supported]
            lines.append(supported_line(name, supported, folded.blocks))
        if chosen.standard_errors:
            out["identifiability"]["standard_errors"] = {term: {"coefficient": k, "standard_error": e}
                                                         for term, (k, e) in chosen.standard_errors.items()}
            out["identifiability"]["refit"] = chosen.refit_test
            lines += uncertain_terms(name, chosen.standard_errors, settings.selection.report_relative_se)
        out["model"] = TargetModel(
            name=name,
            expression=chosen.expression,
            pareto=front_points(candidates, chosen),
            metrics=metrics,
            engine=chosen.engine,
            wall_time_s=elapsed,
        )
        r2v = metrics["validation"]["r2"]
        if not body_frame and not r2v >= r2_threshold:  # body-frame: checked on the composed targets
            out["below"] = float(r2v)
            lines.append(
                f"warning: {name}: validation R^2 {r2v:.6f} is below the threshold {r2_threshold:g}"
            )
        out["expression"] = frozen(chosen.expression)  # the model's own tree, as written (target_pool)
        out["status"] = f"R2={r2v:.6f} complexity {chosen.complexity} ({chosen.engine})"
        bar.close(out["status"])
        out["log"] = f"{name}: R2 {r2v:.6f}, complexity {chosen.complexity}, {chosen.engine}, {elapsed:.1f} s"
        return out

    def fit_target_one_thread(name: str) -> dict[str, Any]:
        """fit_target with BLAS on one thread throughout: the workers share the cores, so BLAS's own
        threads only contend (seed 53's heavy closed loop 123.7 -> 116.4 s wall, every case of the bench
        faster, the same models), and the rounding no longer depends on the machine's core count."""
        with single_threaded_blas():
            return fit_target(name)

    done: dict[str, dict[str, Any]] = {}
    jobs_run = map_targets(fit_target_one_thread, fit_names, processes, LONGEST_FIRST)
    # the heap kept for reuse (heap_reuse; its workers forked inside): seed 71's heavy closed loop 168-183 ->
    # 150-158 s wall, 296-328 -> 271-291 s CPU, interleaved, the same model
    with reused_heap(), contextlib.closing(jobs_run) as results:
        for name, out in results:
            done[name] = out
            if processes > 1:  # the workers showed no bars: one line per target as it comes in
                _Bar(name, progress).close(out["status"])
            if log:
                log(out["log"])
    for name in fit_names:  # in the targets' order, whichever finished first: the same notes, the same order
        out = done[name]
        out["model"] = dataclasses.replace(out["model"], expression=thawed(out["expression"]))
        new_notes = [n for n in out["engine_notes"] if n not in engine_notes]
        engine_notes += new_notes
        warnings += [f"note: {n}" for n in new_notes] + out["lines"]
        for key, per_target in (("evidence", evidence), ("not_excited", not_excited),
                                ("timings", wall), ("gate", gates), ("identifiability", identifiability),
                                ("model", targets_done), ("below", below), ("stats", engine_stats)):
            if key in out:
                per_target[name] = out[key]
    body = None
    if body_frame:
        body = BodyModel(targets_done, primitive_info(), gravity)
        splits = {"train": (X, Y), "pick": (Xp, Yp), "validation": (Xv, Yv)}
        roles_of = {"train": roles.fit, "pick": roles.pick, "validation": roles.validate}
        operators = None
        if weak is not None:  # rows with every target finite (the dataset's rows are)
            operators = {k: weak_rows(roles_of[k].t, roles_of[k].flight, weak) for k in splits}
        predictions = {name: done[name]["predictions"] for name in fit_names if "predictions" in done[name]}
        targets_done = composed_targets(body, targets, splits, operators, predictions)
        for name, t in targets_done.items():  # the threshold is on the composed targets, as reported
            r2v = t.metrics["validation"]["r2"]
            if not r2v >= r2_threshold:
                below[name] = float(r2v)
                warnings.append(
                    f"warning: {name}: validation R^2 {r2v:.6f} is below the threshold {r2_threshold:g}"
                )
    cand = column_collinearity(library_columns, library_names)
    if cand.unidentifiable:
        worst = ", ".join(f"{t.term} ~ {t.partner}" for t in cand.unidentifiable[:3])
        warnings.append(
            f"note: candidate features: condition number {cand.condition_number:.3g}, "
            f"{len(cand.unidentifiable)} of {len(cand.terms)} with VIF > {cand.vif_limit:g} on this flight "
            f"(e.g. {worst}); to separate them: {cand.advice()}"
        )
    flights = [
        {
            "file": f.file,
            "sha256": f.sha256,
            "format": f.format,
            "rows": f.rows,
            "targets_from": f.target_source,
            **({"rows_per_step": dataset.nodes} if dataset.nodes > 1 else {}),  # Dataset.at_step_nodes
        }
        for f in dataset.flights
    ]
    engine_info: dict[str, Any] = {
        "name": engine,
        "loss": loss,
        "seed": seed,
        "budget_generations_per_target": int(budget),
        "selection": "smallest complexity with pick-set loss <= best*(1+rel_tol) + abs_tol*std(pick-set y)",
        "settings": settings.as_dict(),
        "wall_time_s": wall,
        "total_wall_time_s": round(time.perf_counter() - total_start, 3),
        "processes": processes,
        "rows": {
            "fit": int(len(roles.fit)),
            "pick": int(len(roles.pick)),
            "validate": int(len(roles.validate)),
            "dropped": int(dataset.dropped_rows),
        },
    }
    if gates:
        engine_info["sparse_pick_r2"] = gates
    if engine_stats:
        engine_info["stats"] = engine_stats
    if not_excited:
        engine_info["flags"] = [v["flag"] for v in not_excited.values()]
    if weak is not None:
        engine_info["weak_form"] = {
            "test_function": "(1 - s^2)^p over t_j +- T, weights normalised to sum 1",
            "half_window_s": weak.half_window_s, "stride_s": weak.stride_s, "power": int(weak.power),
            "metrics": "every loss and R^2 on the weak rows (data and model integrated alike)",
        }
    if body_frame:
        engine_info["learned_in"] = "body frame FRD: fx fy fz dwx dwy dwz; ax ay az = R f_b + g e_z"
    extra = {
        "data": {**roles.as_dict(), **_evidence(settings.selection, evidence)},
        "checks": {
            "validation_r2_threshold": float(r2_threshold),
            "below_threshold": below,
            "not_excited": {k: {n: v for n, v in d.items() if n != "flag"} for k, d in not_excited.items()},
            "vif_limit": VIF_LIMIT,
            "confounder_vif_limit": CONFOUNDER_VIF_LIMIT,
        },
        "identifiability": {
            "targets": identifiability,
            "engine_notes": engine_notes,  # what the engine could not build features for (discovery)
            "candidate_features": {
                "condition_number": cand.as_dict()["condition_number"],
                "features": len(cand.terms),
                "vif_above_limit": len(cand.unidentifiable),
                "worst": cand.as_dict()["not_identifiable"][:10],
            },
        },
    }
    for line in warnings:
        print(line, file=sys.stderr)
    return Model(
        targets_done, kind="learned", vehicle=vehicle, flights=flights, engine=engine_info, extra=extra,
        body=body,
    )


def _search_space(candidates: list[Candidate], extra: list[sympy.Expr], parts: list, whiteners: list,
                  folded: Any, loss: str, selection: SelectionSettings, X: np.ndarray, y: np.ndarray,
                  target: str) -> SearchSpace:
    """The specification search's space (identification.specification_search): every candidate's terms and the
    polish's extra ones, with their factors (with_factors); a structure becomes a candidate as the
    polish's moves do (fitted on the fit rows, its cross-validated loss on the folds, its self-feedback
    measured)."""
    pool: dict[sympy.Expr, None] = {}
    for c in candidates:
        pool.update(dict.fromkeys(new_shapes(c, pool)))
    pool.update(dict.fromkeys(extra))

    def make(shapes: list[sympy.Expr]) -> Candidate | None:
        c = move_candidate(shapes, folded.terms_loss(shapes, loss), folded, loss, "specification-search")
        if c is not None:
            mark_self_feedback([c], X, y, target)
        return c

    steps = selection.specification_search
    return SearchSpace(lambda start: pool_screen(with_factors([*pool, *start]), parts, whiteners, keep=start),
                       make, steps)


def _excitation(
    name: str,
    candidates: list[Candidate],
    fit: tuple[np.ndarray, np.ndarray],
    loss: str,
    ops: dict[str, Any],
    settings: EngineSettings,
    score: Callable[[list[Candidate]], None],
) -> tuple[Candidate, str, dict[str, Any]] | None:
    """None when the flight excites the target (identification.pareto.excited); else (the minimal physical
    model, fitted on the fit rows, a line saying so, the record for the model file). score: sets a list of
    candidates' held-out losses as the pick's evidence does (the pick rows, or the cross-validation)."""
    constant = fit_terms(("1",), *fit, loss, ops["train"])
    score([constant])
    const_loss = float(constant.holdout_loss) if constant.holdout_loss is not None else float("nan")
    if not np.isfinite(const_loss) or excited(candidates, const_loss, settings.selection):
        return None
    minimal = minimal_candidate(name, *fit, loss, ops["train"])
    score([minimal])
    passing = [c.holdout_loss for c in candidates if admissible(c, settings.selection)]
    best = min((v for v in passing if v is not None and np.isfinite(v)), default=float("nan"))
    composed = " (ax, ay, az are composed from it)" if name in ("fx", "fy", "fz") else ""
    terms = " + ".join(MINIMAL_TERMS.get(name, ("1",)))
    line = (
        f"{name}: not excited by this flight: no candidate whose terms the flight identifies, without "
        f"anti-damping, has a pick {loss} loss below the constant's {const_loss:.3g} by "
        f"{settings.selection.min_gain:.0%} (best {best:.3g}); what the candidates fit is noise or an "
        f"artefact, so {name} gets the minimal physical model (terms {terms}){composed}: "
        + " ".join(text for _, text in equation_text(name, minimal.expression)).lstrip("+ ")
        + " (3 significant digits)"
    )
    record = {
        "constant_pick_loss": const_loss,
        "best_pick_loss": best,
        "min_gain": settings.selection.min_gain,
        "model_terms": list(MINIMAL_TERMS.get(name, ("1",))),
        "flag": line,
    }
    return minimal, line, record


def _gap_rows(t: np.ndarray, operator: Any, gap_s: float) -> int:
    """Rows either side of a held-out fold its fits leave out: the weak windows' overlap (weak rows), else
    the rows within gap_s (s) at the rows' median sampling interval (the derivative windows' reach)."""
    if operator is not None:
        return overlap_lag(operator)
    dt = np.diff(np.asarray(t, float))
    dt = dt[dt > 0]
    return int(np.ceil(gap_s / float(np.median(dt)))) if dt.size else 0


def _evidence(selection: SelectionSettings, per_target: dict[str, str]) -> dict[str, Any]:
    """What the pick scored candidates on (per target) and which rows fitted the chosen coefficients."""
    cv = any(v.startswith("blocked") for v in per_target.values())
    kinds = set(per_target.values())
    return {
        "pick_evidence": next(iter(kinds)) if len(kinds) == 1 else per_target if kinds else "pick rows",
        "coefficients_fitted_on": "fit and pick rows (the structure chosen, then refit on both)"
        if cv or selection.refit_with_pick_rows else "fit rows",
    }
