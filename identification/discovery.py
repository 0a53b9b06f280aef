"""The discovery engine: finds body-frame physics its library does not hold, from primitives.

In the spirit of SISSO (Ouyang et al. 2018), per target:
1. grow candidate features from the body-frame primitives by operators, in rungs, with dimensional analysis
   pruning invalid combinations (identification.feature_space);
2. sure independence screening: rank every feature by |correlation| with the current residual and add the
   best `screen` to the pool;
3. sparsify the pool (STLSQ threshold sweep, backward elimination and forward selection, as the sparse
   engine: identification.sparse); every active set is a candidate; the held-out pick gives the residual;
4. repeat 2-3 on the residual, at most `rounds` rounds, until `patience` rounds in a row leave the picked
   model no better on the held-out rows (small effects surface once the large ones are fitted; a round
   that finds nothing new costs the next one, at most);
5. genetic programming (pyoperon), seeded with the primitives and the picked model's features, fits the
   picked model's residual for a fixed number of generations (always: no threshold gates it); the front's
   expressions come back expanded into their additive terms, which join the picked model's features in one
   more sparse fit (refit, pruned and identified term by term like any feature);
6. the pick is polished by term substitution (DiscoveryEngine._polish): one term swapped for one pool
   feature, or removed, at a time; a move is kept when the pick's identification rules hold and (rule
   "occam") its pick-row loss is lower by more than noise at no more complexity, or it lowers the complexity
   without being worse by more than noise and within the pick's tolerance (the pick then decides). Before
   that, a model only the VIF rule sets aside (the pick without it) is rewritten by merging two of its terms
   into one feature (DiscoveryEngine._merge_repair): a family of terms written in a basis the VIF rule rejects
   and in another it accepts (u2 wz + u4 wz beside wz (u1+u2+u3+u4) for wz (u1-u2+u3-u4)).
The engine learns in the body frame (`frame = "body"`): targets fx fy fz (specific force FRD, m/s^2) and
dwx dwy dwz (FRD, rad/s^2); candidates' expressions are in the primitive names (identification.body_frame).
Budgets are counts, not seconds (the time budget is ignored), so the same seed gives the same model.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import itertools
import time
import warnings
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import sympy

from bridge.errors import UserError
from identification.body_frame import PRIMITIVE_SYMBOLS, PRIMITIVES, primitive_matrix
from identification.candidate import Candidate, Progress
from identification.collinearity import term_identification, term_shapes, term_t_ratios
from identification.column_buffer import ColumnBuffer
from identification.engine_settings import POLISH_RULES, DiscoverySettings, SelectionSettings, SparseSettings
from identification.feature_space import (
    OPERATORS,
    FeatureSpace,
    grow_products,
    grow_unary,
    power_unit,
)
from identification.hub_law import HUB_LAW_SHARES, HUB_PRIMITIVES, HubLaw, fit_hub_law, thrust_shares
from identification.library import Feature
from identification.metrics import LOSSES
from identification.metrics import loss as loss_fn
from identification.model_file import ExpressionError, complexity, parse_expression
from identification.paired_loss import paired_loss_t
from identification.pareto import admissible, attach_holdout, pick_limit, select, within_tolerance
from identification.replacement import replacements
from identification.robust_weights import huber_weights
from identification.rows_cache import cached
from identification.sparse import (
    LeastSquaresProblem,
    lstsq_by_qr,
    single_threaded_blas,
    sparse_active_sets,
    sparse_expression,
)
from identification.weak_form import overlap_lag
from identification.weak_noise import Whitener

# Decimal places of pyoperon's infix formatter (fixed-point): 25 keeps ~17 significant digits down to 1e-8.
_PRECISION = 25


def check_settings(settings: DiscoverySettings) -> None:
    """UserError for an unknown primitive or operator name in the discovery settings."""
    bad = [p for p in settings.primitives if p not in PRIMITIVES]
    if bad:
        raise UserError(
            f"discovery settings: unknown primitive {bad[0]!r}", hint=f"known: {', '.join(PRIMITIVES)}"
        )
    bad = [o for o in settings.operators if o not in OPERATORS]
    if bad:
        raise UserError(
            f"discovery settings: unknown operator {bad[0]!r}", hint=f"known: {', '.join(OPERATORS)}"
        )
    if settings.polish_rule not in POLISH_RULES:
        raise UserError(f"discovery settings: key 'polish_rule' must be one of {', '.join(POLISH_RULES)}, "
                        f"got {settings.polish_rule!r}", hint="occam (default): noise decides each move")
    if not (settings.polish_z > 0 and np.isfinite(settings.polish_z)) or settings.polish_blocks < 2:
        raise UserError("discovery settings: keys 'polish_z' > 0 and 'polish_blocks' >= 2, got "
                        f"{settings.polish_z} and {settings.polish_blocks}", hint="polish_z 2, blocks 20")
    if settings.polish_passes < 0 or settings.polish_tries < 1:
        raise UserError("discovery settings: keys 'polish_passes' >= 0 and 'polish_tries' >= 1, got "
                        f"{settings.polish_passes} and {settings.polish_tries}", hint="polish_passes 0: off")
    if not settings.primitives:
        raise UserError("discovery settings: no primitives", hint=f"choose from {', '.join(PRIMITIVES)}")
    if settings.operon_rows < 0:
        raise UserError(f"discovery settings: key 'operon_rows' must be >= 0, got {settings.operon_rows}",
                        hint="0: the GP reads every fit row")
    if settings.hub_law_fits < 0 or settings.hub_law_powers < 1 or settings.hub_law_evaluations < 1:
        raise UserError("discovery settings: keys 'hub_law_fits' >= 0, 'hub_law_powers' >= 1 and "
                        f"'hub_law_evaluations' >= 1, got {settings.hub_law_fits}, "
                        f"{settings.hub_law_powers} and {settings.hub_law_evaluations}",
                        hint="hub_law_fits 0: off; powers 4; evaluations 400")
    if not 0.0 <= settings.hub_law_min_height < 1.0:
        raise UserError("discovery settings: key 'hub_law_min_height' must be in [0, 1), got "
                        f"{settings.hub_law_min_height}",
                        hint="the lowest hub height allowed, as a fraction of the CG's height: 0.25; 0: any "
                             "hub above the ground")
    if settings.hub_law_shares not in HUB_LAW_SHARES:
        raise UserError("discovery settings: key 'hub_law_shares' must be one of "
                        f"{', '.join(HUB_LAW_SHARES)}, got {settings.hub_law_shares!r}",
                        hint="thrust: each rotor's far-field thrust term; arms: the fitted hubs' arms")
    if not 0.0 <= settings.abs_sign_share <= 1.0:
        raise UserError(f"discovery settings: key 'abs_sign_share' must be in [0, 1], got "
                        f"{settings.abs_sign_share}", hint="0.05: |x| only where x reaches both signs")


class _Columns:
    """Feature values for any X (N,16), computed from the space's recipes, cached for the last arrays seen."""

    def __init__(self, space: FeatureSpace):
        self.space = space
        self._cache: list[tuple[np.ndarray, np.ndarray, dict[int, np.ndarray], dict[int, float]]] = []

    def primitives(self, X: np.ndarray) -> np.ndarray:
        """The primitive matrix of X (N, n_primitives)."""
        return self._entry(X)[0]

    def __call__(self, X: np.ndarray, indices: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        P, cache, _ = self._entry(X)
        return self.space.columns(P, indices, cache, out)

    def means(self, X: np.ndarray, indices: np.ndarray) -> np.ndarray:
        """Each feature's mean over X's rows (len(indices),), NaN for one not finite on every row."""
        P, cache, means = self._entry(X)
        for i in indices:
            if int(i) not in means:
                col = self.space.columns(P, [int(i)], cache)[:, 0]
                means[int(i)] = float(np.mean(col)) if np.all(np.isfinite(col)) else float("nan")
        return np.asarray([means[int(i)] for i in indices])

    def _entry(self, X: np.ndarray) -> tuple[np.ndarray, dict[int, np.ndarray], dict[int, float]]:
        for key, P, cache, means in self._cache:
            if key is X:
                return P, cache, means
        P = primitive_matrix(X, self.space.primitives)
        cache: dict[int, np.ndarray] = {}
        means: dict[int, float] = {}
        self._cache = [(X, P, cache, means), *self._cache[:3]]
        return P, cache, means


class DiscoveryEngine:
    """Features grown from body-frame primitives, screened, sparsified, then GP on the residual."""

    frame = "body"

    def __init__(
        self,
        settings: DiscoverySettings | None = None,
        sparse: SparseSettings | None = None,
        name: str = "discovery",
        selection: SelectionSettings | None = None,
    ):
        self.settings = settings or DiscoverySettings()
        self.selection = selection or SelectionSettings()  # the final pick's rules (the polish keeps them)
        check_settings(self.settings)
        # no simpler-term swaps: over a grown pool they multiply the candidates for little gain
        self.sparse = dataclasses.replace(
            sparse or SparseSettings(), forward_terms=self.settings.max_terms, swap_max_terms=0,
            thresholds=min((sparse or SparseSettings()).thresholds, self.settings.thresholds),
        )
        self.name = name
        self._target: str | None = None
        # weak form (identification.weak_form): (V of the fit rows, V of the holdout rows); set by identify
        self.weak: tuple[Any, Any] | None = None
        # the fit rows' whitener when the log states its targets' noise (weak_noise; set by identify): the
        # t ratios of the pick's identification rule under that noise (collinearity.term_identification)
        self.noise: Whitener | None = None
        # the rows the pick measures a candidate's terms on, when not the fit rows (set by identify:
        # FoldedRows.identification, the fit and pick rows; SelectionSettings.identify_on_pick_rows): term
        # shapes -> (weakest t ratio, largest VIF). The polish and the merge repair then keep the moves the
        # pick would
        self.identification: Callable[[list[sympy.Expr]], tuple[float, float]] | None = None
        self.timings: dict[str, float] = {}
        self.stats: dict[str, object] = {}
        self._features: dict[int, np.ndarray] = {}  # id(candidate) -> its feature indices in the space
        self._path_terms = self.settings.max_terms  # the sparse paths' length (_longer_paths)
        self.notes: list[str] = []  # identifiability notes of the last fit (identify prints them)

    def build_space(self, X: np.ndarray) -> FeatureSpace:
        """The grown feature space for training data X (N,16): rungs 1 and 2 (rung 3 is grown in fit)."""
        s = self.settings
        P = primitive_matrix(X, s.primitives)
        space = grow_unary(s.primitives, s.operators, P, s.inverse_span, s.inverse_powers,
                           near_inverse_powers=s.near_inverse_powers, near_spread=s.near_spread,
                           abs_sign_share=s.abs_sign_share, min_spread=s.min_spread)
        unary = list(range(len(space)))
        if s.rungs >= 2 and "mul" in s.operators:
            grow_products(space, unary, unary, 2)
        return space

    @property
    def round_selection(self) -> SelectionSettings:
        """The pick between rounds (whose residual the next round screens against): this engine's selection,
        its tolerances as the user set them, without its identification rules (t ratio, VIF).

        A round's models are incomplete: their residual is the physics still to find, smooth, so its
        effective sample size is tens of rows and every t ratio is small; which few pass is chance (with t
        ratios on a robust scale, 2 of the first round's 42 candidates of fang-chen-aero's dwx passed and the
        screening stayed on a 2-term model, R^2 0.989); the rules are for the final pick (identify), which
        sees every round's candidates."""
        return dataclasses.replace(self.selection, min_t=0.0, max_vif=float("inf"))

    def fit(
        self,
        X: np.ndarray,
        y: np.ndarray,
        target: str,
        budget: int,
        seed: int,
        loss: str = "absolute",
        progress: Progress | None = None,
        holdout: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> list[Candidate]:
        """Candidates for one body-frame target (expressions in primitive names); budget: GP generations."""
        if loss not in LOSSES:
            raise ValueError(f"loss must be one of {LOSSES}")
        X = np.asarray(X, dtype=float)
        y = np.asarray(y, dtype=float)
        self._target = target
        if holdout is None:
            cut = int(round(0.8 * len(y)))
            X, Xh, y, yh = X[:cut], X[cut:], y[:cut], y[cut:]
        else:
            Xh, yh = np.asarray(holdout[0], float), np.asarray(holdout[1], float)
        with single_threaded_blas():
            return self._fit(X, y, Xh, yh, seed, loss, progress, int(budget))

    def _fit(
        self,
        X: np.ndarray,
        y: np.ndarray,
        Xh: np.ndarray,
        yh: np.ndarray,
        seed: int,
        loss: str,
        progress: Progress | None,
        budget: int,
    ) -> list[Candidate]:
        s = self.settings
        start = time.perf_counter()
        self._features = {}
        key = (s, _rows_key(X))
        room = max(s.hub_law_fits, 1)  # a hub law's column each, appended in place (column_buffer)
        # the matrices grown by columns: the features F, their standardized copy Z, Z's NaN-free copy and F
        # column-major (the last two made when first needed); the six targets of one flight share them
        grown: dict[str, ColumnBuffer] = {}
        if s.rungs < 3 and _LAST_SPACE.get("key") == key:
            space, grown = _LAST_SPACE["space"], _LAST_SPACE["grown"]
            F, Z = grown["F"].truncate(len(space)), grown["Z"].truncate(len(space))
            for k in ("Zf", "Fc"):  # a target before this one may have appended its hub laws
                if k in grown:
                    grown[k].truncate(len(space))
        else:
            space = self.build_space(X)
            grown["F"] = ColumnBuffer(len(X), len(space), room)
            F = _Columns(space)(X, np.arange(len(space)), out=grown["F"].view())
            grown["Z"] = _standardized_buffer(F, room)
            Z = grown["Z"].view()
            _LAST_SPACE.clear()
            if s.rungs < 3:  # rung 3 grows the space per target: not shared
                _LAST_SPACE.update(key=key, space=space, grown=grown)
        columns = _Columns(space)
        if s.rungs >= 3 and "mul" in s.operators:
            scores = _screen_scores(Z, y)
            rung2 = [i for i in np.argsort(-scores, kind="stable") if space.rungs[i] == 2][: s.beam]
            unary = [i for i in range(len(space)) if space.rungs[i] == 1]
            added = grow_products(space, rung2, unary, 3)
            if added:
                F = grown["F"].append(columns(X, np.asarray(added, int)))
                grown["Z"] = _standardized_buffer(F, room)
                Z = grown["Z"].view()
        self.timings = {"grow": time.perf_counter() - start}
        self.stats = {"features": len(space), "pruned": dict(space.pruned)}
        # what the flight cannot identify, for identify's terminal and model file (identifiability notes)
        self.notes = [f"{why}: none of its features is built (a term times it cannot be told from the term "
                      "alone on this flight; vary it more to identify its effects)"
                      for why in space.pruned if "barely varies" in why]
        self.notes += inverse_notes(s, X)
        weak, weak_h = self.weak or (None, None)
        y_point = y
        if weak is not None:  # every column and the target integrated against the test functions
            grown = {"F": ColumnBuffer.holding(np.asarray(weak @ F), room)}
            F = grown["F"].view()
            grown["Z"] = _standardized_buffer(F, room)
            Z = grown["Z"].view()
            y = weak @ y
        scale = float(np.std(yh if weak_h is None else weak_h @ yh)) if len(yh) else 1.0
        basis = _Basis(len(y))
        # rung 1 always in (combinations first: where a combination and its members are dependent, the
        # combination stands for them); later features only where independent of the pool
        pool: list[int] = basis.add_first(F, [i for i in range(len(space)) if space.rungs[i] == 1])
        candidates: list[Candidate] = []
        seen: set[frozenset[int]] = set()
        residual = y.copy()
        weights: np.ndarray | None = None  # Huber row weights from the last round's model (absolute loss)
        swaps: list[int] = []  # features that would replace a term of the last round's model (replacement)
        best: Candidate | None = None
        stale = 0  # rounds in a row whose pick is no better on the held-out rows
        off = np.zeros(len(space), bool)  # features out of the screening (the height series once a law is in)
        heights = space.height_features()  # what the forward path from the pick never adds
        zf: tuple | None = None  # (Z, its NaN-free copy, column sums of squares, usable columns)
        correlations: dict[int, np.ndarray] = {}  # per term, |correlation| with Z's columns (replacements)
        # (F, F column-major): the replacement screening gathers some 40 columns per term of the pick, 3 ms
        # a gather from the row-major F of a heavy closed loop (1,600 columns), 0.1 ms from this copy
        by_column: tuple[np.ndarray, np.ndarray] | None = None
        # a hub law is fitted where the rounds would stop (the pick as complete as the series lets it be), at
        # most hub_law_fits times; each law round is followed by rounds that screen its residual
        laws, fit_law = 0, False
        series: tuple | None = None  # the state the first hub law was added to
        before: tuple | None = None  # the state the last hub law was added to
        rnd, last = 0, max(s.rounds, 1)  # rounds run while rnd < last (a hub law adds rounds)
        self._path_terms = s.max_terms  # the sparse paths' length; grows while the round's pick reaches it
        while rnd < last:
            law_now = False
            if fit_law:
                fit_law = False
                laws += 1
                added = self._add_hub_law(best, space, columns, F, y, X, pool)
                if added is None:
                    # the series' rounds had ended where the law was due: they end as with no law
                    key = "hub_law" if series is None else "hub_law_refit"
                    self.stats[key] = ("none: no finite fit with every hub above "
                                       f"{s.hub_law_min_height:g} of the CG's height at every row and "
                                       "nearer the CG than the flight's median height")
                    break
                # the series' state, to return to when the law's rounds end no better (hub_law_evidence)
                before = (best, len(candidates), space, columns, F, Z, pool)
                series = series or before
                space, law, columns = added
                F = grown["F"].append(self._on_fit_rows(columns(X, np.asarray([law]))))
                z_law = _standardized(F[:, [law]])
                Z = grown["Z"].append(z_law)
                if zf is not None:  # Z's NaN-free copy grown alike (as np.nan_to_num(Z) would be)
                    zf = (Z, grown["Zf"].append(np.nan_to_num(z_law, nan=0.0)))
                    zf += (np.sum(zf[1] * zf[1], axis=0), np.all(np.isfinite(Z[:1]), axis=0))
                if by_column is not None:
                    by_column = (F, grown["Fc"].append(F[:, [law]]))
                correlations = {}  # per term over Z's columns: one more now
                off = heights = space.height_features()
                pool = [i for i in pool if not off[i]] + basis.add_first(F, [law])
                swaps = [i for i in swaps if not off[i]]
                law_now = law in pool
            model_terms = self._features.get(id(best), np.zeros(0, int))
            model_cols = F[:, model_terms]
            if zf is None or zf[0] is not Z:  # Z's NaN-free copy and column sums, once per space
                if "Zf" not in grown or grown["Zf"].used != Z.shape[1]:
                    grown["Zf"] = ColumnBuffer.holding(Z, room)
                    np.nan_to_num(grown["Zf"].view(), nan=0.0, copy=False)
                zf = (Z, grown["Zf"].view())
                zf += (np.sum(zf[1] * zf[1], axis=0), np.all(np.isfinite(Z[:1]), axis=0))
                correlations = {}
            scores = _projected_scores(Z, residual if weights is None else weights * residual, model_cols,
                                       prepared=zf[1:])
            scores[off] = -np.inf
            new = basis.add_first(F, swaps)  # replacement screening first
            # a proposed swap that is a combination of pool features takes the place of one of them
            swapped = _swap_in_combinations(F, pool, [i for i in swaps if i not in new],
                                            {i for i in pool if space.rungs[i] == 1}, scores,
                                            _model_t(F, model_terms, y), basis=basis)
            scores[pool] = -np.inf
            order = np.argsort(-scores, kind="stable")
            limit = s.screen + len(swaps) - len(new)
            new += basis.add_first(F, order[np.isfinite(scores[order])], limit=limit)
            if not new and not swapped and not law_now:
                if not self._law_due(best, space, laws):
                    break
                fit_law, last, rnd = True, max(last, rnd + 2), rnd + 1
                continue
            pool += new
            ids = np.asarray(pool)
            at = {int(i): k for k, i in enumerate(pool)}
            start_at = [at[int(i)] for i in model_terms if int(i) in at] if s.forward_from_pick else None
            round_cands = self._sparsify(
                [space.expressions[i] for i in pool], [f"rung{space.rungs[i]}" for i in pool], F[:, pool],
                list(pool), lambda X_, js, ids=ids, cols=columns: cols(X_, ids[js]), y, loss, seen,
                space_indices=ids, weights=weights, start=start_at,
                addable=None if start_at is None else ~heights[ids],
                means=lambda X_, js, ids=ids, cols=columns: cols.means(X_, ids[js]))
            attach_holdout(round_cands, Xh, yh, loss, weak_h)
            candidates += round_cands
            previous, best = best, select(candidates, self.round_selection, scale=scale)
            residual = y - (best.evaluate(X) if weak is None else weak @ best.evaluate(X))
            if loss == "absolute":  # the few rows with large target errors do not choose the terms
                weights = huber_weights(residual)
            if by_column is None or by_column[0] is not F:
                if "Fc" not in grown or grown["Fc"].used != F.shape[1]:
                    grown["Fc"] = ColumnBuffer.holding(F, room, order="F")
                by_column = (F, grown["Fc"].view())
            swaps = replacements(by_column[1], Z, y, [int(i) for i in self._features.get(id(best), [])], pool,
                                 weights, correlations=correlations)
            swaps = [i for i in swaps if not off[i]]
            if progress:
                progress(0.7 * (rnd + 1) / max(s.rounds, 1),
                         f"round {rnd + 1}: pool {len(pool)}, pick loss {best.holdout_loss:.3g}")
            stale = stale + 1 if previous is not None and not _better(best, previous, scale) else 0
            if self._longer_paths(best):  # the longer paths get their rounds (within the budget)
                stale = 0
            stop = not law_now and (stale >= max(s.patience, 1) or _exact(best, scale))
            if law_now:
                stale = 0
            # a law is fitted where the series' own rounds end, so a law not kept leaves the model the
            # series reached (the same as with no law)
            if (stop or rnd + 1 >= last) and not law_now and self._law_due(best, space, laws):
                fit_law, stale, last = True, 0, max(last, rnd + 2 + max(s.patience - 1, 0))
            elif stop:
                break
            rnd += 1
        self.stats["rounds"] = min(rnd + 1, last)
        # a refit law (its rounds started from the last law's pick) is kept only when its rounds beat that
        # pick, and the first law only when the model then beats the series'
        if before is not series and not self._keep_law(best, before[0], Xh, yh, loss, space.laws[-1],
                                                       "hub_law_refit"):
            best, n, space, columns, F, Z, pool = before
            del candidates[n:]
        if series is not None and not self._keep_law(best, series[0], Xh, yh, loss, space.laws[-1]):
            best, n, space, columns, F, Z, pool = series
            del candidates[n:]
        self.timings["sparse"] = time.perf_counter() - start - self.timings["grow"]
        self.stats["pool"] = len(pool)
        # nearest_features' and residual_features' space, with Z's NaN-free copy when the rounds made one
        # for this Z, and the fit rows' columns as screened (F)
        self._final = (space, columns, Z, zf[1] if zf is not None and zf[0] is Z else None, X, F)
        if best is not None and budget > 0:
            op_start = time.perf_counter()
            gp = self._operon(best, columns, X, y_point, Xh, yh, seed, loss, budget)
            attach_holdout(gp, Xh, yh, loss, weak_h)
            candidates += gp
            self.timings["operon"] = time.perf_counter() - op_start
        if candidates and s.polish_passes > 0:
            polish_start = time.perf_counter()
            if s.polish_merge:  # the model past the VIF cap, rewritten by merges (_merge_repair)
                loose = select(candidates, self._no_vif_rule(), scale=scale)
                capped = dataclasses.replace(self.selection, vif_rule="cap")
                if not admissible(loose, capped) and admissible(loose, self._no_vif_rule()):
                    candidates += self._merge_repair(loose, columns, F, y, X, Xh, yh, loss, scale)
            pick = select(candidates, self.selection, scale=scale)
            candidates += self._polish(pick, [int(i) for i in pool], columns, F, y, X, Xh, yh, loss, scale,
                                       pick_limit(candidates, self.selection, scale))
            self.timings["polish"] = time.perf_counter() - polish_start
        if progress:
            progress(1.0, f"{len(candidates)} candidates")
        return candidates

    def nearest_features(self, shapes: Sequence[sympy.Expr], count: int) -> list[sympy.Expr]:
        """For each shape (an expression in the primitives), the `count` features of the last fit's space
        of the same primitives most correlated with it on the fit rows (|correlation| of the standardized
        columns), no height feature and not the shape itself: its shape twins (wz^2 beside |wz|), which the
        cross-validated polish may swap in (identification.cv_polish). The same primitives, as the features
        most correlated overall are the term times a nearly constant factor (|wz| sqrt(u1^2 + .. + u4^2)).
        [] before a fit or with count < 1."""
        final = getattr(self, "_final", None)
        if final is None or count < 1 or not shapes:
            return []
        space, columns, Z, clean, X, _ = final
        exprs = space.expressions[: Z.shape[1]]
        variables = [frozenset(map(str, e.free_symbols)) for e in exprs]
        M = _standardized(self._term_columns(list(shapes), columns, X))
        clean = np.nan_to_num(Z, nan=0.0) if clean is None else clean
        with np.errstate(all="ignore"):
            corr = np.abs(clean.T @ np.nan_to_num(M, nan=0.0)) / max(len(M), 1)
        corr[space.height_features()[: len(corr)]] = -1.0
        out: dict[sympy.Expr, None] = {}
        for k, shape in enumerate(shapes):
            own = frozenset(map(str, shape.free_symbols))
            if not own or not np.all(np.isfinite(M[:, k])):
                continue
            near = [i for i in np.argsort(-corr[:, k], kind="stable")
                    if corr[i, k] > 0.0 and variables[i] == own and exprs[i] != shape]
            for i in near[:count]:
                out.setdefault(exprs[i], None)
        return list(out)

    def residual_features(self, parts: Sequence[tuple[np.ndarray, np.ndarray | None]], residual: np.ndarray,
                          count: int, skip: Sequence[sympy.Expr] = ()) -> list[sympy.Expr]:
        """The `count` features of the last fit's space most correlated (|correlation|) with `residual` over
        the rows of `parts` ((X (N,16), the weak form's test functions (N',N) or None) each, stacked in that
        order as residual's rows), no height feature and none of `skip`. The engine screens on the fit rows
        alone: a term only the pick rows excite (a yaw coupling of a flight that yaws late) is in none of its
        candidates, and the pick's cross-validated residual over both parts points at it (cv_polish). []
        before a fit or with count < 1."""
        final = getattr(self, "_final", None)
        if final is None or count < 1 or not parts:
            return []
        space, columns, Z, _, fitted, F_fit = final
        exprs = space.expressions[: Z.shape[1]]
        index = np.arange(len(exprs))
        r = np.asarray(residual, float)
        weight = np.isfinite(r).astype(float)  # a row no fold holds out (in a gap) has no prediction
        r = np.where(weight > 0.0, r, 0.0)
        r = weight * (r - float(r @ weight) / max(float(weight.sum()), 1.0))
        n, cross, sums, squares, start = float(weight.sum()), 0.0, 0.0, 0.0, 0
        with np.errstate(all="ignore"):
            for X, op in parts:  # sums over the parts' rows, no stacked copy of their columns
                rows = len(X) if op is None else op.shape[0]
                same = X is fitted or (X.shape == fitted.shape and np.array_equal(X, fitted))
                if same and F_fit.shape == (rows, len(exprs)):
                    F = F_fit  # the fit rows' columns, as the engine screened them
                else:
                    F = columns(X, index) if op is None else np.asarray(op @ columns(X, index))
                w, rr = weight[start: start + rows], r[start: start + rows]
                start += rows
                cross = cross + rr @ F
                sums = sums + w @ F
                squares = squares + np.einsum("ij,ij,i->j", F, F, w)
            variance = squares - sums * sums / max(n, 1.0)
            corr = np.abs(cross) / np.sqrt(variance * float(r @ r))
        corr[~np.isfinite(corr)] = -1.0
        corr[space.height_features()[: len(corr)]] = -1.0
        skipped = set(skip)
        order = np.argsort(-corr, kind="stable")
        return [exprs[i] for i in order if corr[i] > 0.0 and exprs[i] not in skipped][:count]

    def _law_due(self, best: Candidate | None, space: FeatureSpace, laws: int) -> bool:
        """Whether to fit a hub law now: fewer than hub_law_fits fitted, the flight reaches near the ground
        (the space holds the ground-plane gradients) and the pick of the rounds so far holds height
        features."""
        s = self.settings
        if best is None or laws >= s.hub_law_fits or not any(r.op == "tilt" for r in space.recipes):
            return False
        terms = self._features.get(id(best), ())
        mask = space.height_features()
        return any(mask[int(i)] for i in terms)

    def _add_hub_law(
        self,
        best: Candidate,
        space: FeatureSpace,
        columns: _Columns,
        F: np.ndarray,
        y: np.ndarray,
        X: np.ndarray,
        pool: list[int] | None = None,
    ) -> tuple[FeatureSpace, int, _Columns] | None:
        """The pick's height terms refit as one hub law (identification.hub_law) beside its other terms, the
        law added to a copy of the space: (that space, the law's index, its columns), or None (no
        finite fit, or the law already in the space). F, y: fit rows (weak rows in the weak form); X: the fit
        rows' variables."""
        s = self.settings
        mask = space.height_features()
        rest_idx = [int(i) for i in self._features.get(id(best), ()) if not mask[int(i)]]
        rest_idx += [int(i) for i in (pool or ()) if not mask[int(i)] and int(i) not in rest_idx]
        weak = (self.weak or (None, None))[0]
        rest = np.hstack([self._on_fit_rows(np.ones((len(X), 1))), F[:, rest_idx]])
        P = columns.primitives(X)
        inputs = P[:, [space.primitives.index(n) for n in HUB_PRIMITIVES]]
        clock = time.perf_counter()
        # a law refit starts where the last one ended, a first law with every hub at the CG: not where
        # another target's law ended, which would make a target's model depend on which targets its process
        # fitted before it (identification.target_pool fits them side by side)
        start = np.asarray(space.laws[-1].offsets) if space.laws else None
        arm = {"fx": "force", "fy": "force", "fz": "force", "dwx": "roll", "dwy": "pitch"}.get(self._target) \
            if s.hub_law_shared else None
        if arm is not None and s.hub_law_shares == "thrust":
            # the ground multiplies each rotor's own thrust: its share is the pick's far-field u_i^2 term
            shares = thrust_shares(best.expression)
            arm = arm if shares is None else shares / np.max(np.abs(shares))
        fitted = fit_hub_law(inputs, y, rest, s.hub_law_powers, weak, s.hub_law_evaluations, start,
                             s.hub_law_airspeed or (s.hub_law_refit_airspeed and bool(space.laws)), arm,
                             s.hub_law_min_height, rational=s.hub_law_rational)
        self.timings["hub_law"] = self.timings.get("hub_law", 0.0) + time.perf_counter() - clock
        if fitted is None:
            return None
        grown = space.copy()
        # unit of u_i^2: the law's coefficients carry the rest
        index = grown.add_law(fitted, power_unit(PRIMITIVES["u1"].unit, 2))
        if index is None:
            return None
        return grown, index, _Columns(grown)

    def _keep_law(
        self,
        best: Candidate,
        series_best: Candidate,
        Xh: np.ndarray,
        yh: np.ndarray,
        loss: str,
        law: HubLaw,
        key: str = "hub_law",
    ) -> bool:
        """Whether the pick of the rounds a hub law was added to is kept over the pick its series had
        reached: with hub_law_evidence only when better on the pick rows by more than polish_z standard
        errors (paired_loss_t). Judged after the law's rounds, not when it is fitted: the law is fitted
        beside a pick the series has shaped (terms the series held in its place are missing), so at first
        it is seldom better, and the terms it lets the rounds find are its evidence. A flight whose tilts
        keep the hubs' offsets small against the height has a series as good, and the law's sixteen
        coefficients then fit the targets' errors: the series stays. A refit law is judged the same way
        against the pick the last law's rounds reached (series_best; key "hub_law_refit" in the stats)."""
        s = self.settings
        t = paired_loss_t(self._pick_rows(yh), self._pick_rows(best.evaluate(Xh)),
                          self._pick_rows(series_best.evaluate(Xh)), loss, s.polish_blocks)
        self.stats[f"{key}_t"] = float(t)
        if s.hub_law_evidence and not t < -s.polish_z:
            against = "the series'" if key == "hub_law" else "the last law's"
            self.stats[key] = f"fitted, not kept: its rounds' pick no better than {against} on the pick rows"
            return False
        self.stats["hub_offsets_m"] = [list(r) for r in law.offsets]
        self.stats[key] = "kept" + (" (with the hubs' airspeed)" if law.airspeed else "")
        return True

    def _polish(
        self,
        pick: Candidate,
        pool: list[int],
        columns: _Columns,
        F: np.ndarray,
        y: np.ndarray,
        X: np.ndarray,
        Xh: np.ndarray,
        yh: np.ndarray,
        loss: str,
        scale: float,
        limit: float | None = None,
    ) -> list[Candidate]:
        """Term-substitution polish of the pick: a local search that swaps one term of the picked model for
        one pool feature at a time. The sparse paths grow or shrink a model one term at a time along a
        path; a model whose term is a near-copy of the true one (wz^2 |wz| for wz^2, both even in wz) is a
        local optimum they never leave, since the true term only helps once the copy is out (fang-chen-aero's
        dwy: no candidate of the paths held wz^2, yet swapping it in was better on the pick rows).
        Each pass ranks every (term, pool feature) swap by the least-squares residual of the swapped model on
        the fit rows (term_substitutions: one projection of the pool, no refit) and refits the best
        `polish_tries` as the sparse candidates are refit (least squares, then the absolute-error refit);
        every refit must pass the pick's identification rules (t ratio >= min_t, VIF <= max_vif).
        polish_rule "occam" (the default) and "tolerance": the pass also refits the best `polish_tries` swaps
        that lower the model's complexity (a pool feature smaller than the term it replaces), the best
        `polish_tries` removals of one term (term_removals) and, with `polish_joins`, the best `polish_tries`
        joins of two terms into one pool feature (term_merges: two stand-ins such as |vb| + vb^2 |vb| for a
        true vb^2, where neither one-term swap is better while the other stays in). "occam" decides by noise:
        each refit's pick-row loss against the current model's as a paired t ratio (paired_loss_t: the rows'
        loss differences, the standard error from `polish_blocks` contiguous blocks' means). A move better by
        more than `polish_z` standard errors that adds no complexity is taken, the lowest loss first (with
        `polish_grow`, also one that adds complexity when it beats the current model by the pick's tolerance
        as well); else the simplest move that lowers the complexity, is not worse by more than `polish_z`
        standard errors and stays within the pick's tolerance of the best loss seen (`limit`: the pick's limit
        over every candidate so far, pareto.pick_limit); else the pass stops. "tolerance" uses the pick's
        rel_tol/abs_tol in place of the standard errors (on noise-free targets rel_tol is no noise level: it
        let |wz| stand for a small wz^2). So noise-level gains are never chained; what the polish returns, the
        pick weighs as any candidate.
        polish_rule "margin" (session 7): keeps the lowest-loss swap when it beats the current model's
        pick loss by more than 0.1 % (_better).
        At most `polish_passes` passes. Budgets are counts; deterministic (stable orders).
        F, y: the fit rows' feature matrix and target (weak rows when the weak form is on); the candidates
        returned (each accepted move's model) join the others for identify's pick."""
        s = self.settings
        sel = self.selection
        terms = _product_factors(pick.expression)
        if not terms or pick.holdout_loss is None or not np.isfinite(pick.holdout_loss):
            return []
        exprs = columns.space.expressions
        sizes = {i: complexity(exprs[i]) for i in pool}
        # a swap changes one term, not the constant: the constant stays in (or out) as in the current model,
        # and one more move toggles it (polish_constant)
        constant = any(t.is_number for t in sympy.Add.make_args(pick.expression))
        occam = s.polish_rule in ("occam", "tolerance")
        yv = self._pick_rows(yh)
        best_seen = float(pick.holdout_loss)
        if limit is None or not np.isfinite(limit):
            limit = within_tolerance(best_seen, sel, scale)
        out: list[Candidate] = []
        current = pick
        heights = columns.space.height_features() if s.polish_split_width >= 2 else np.zeros(len(exprs), bool)
        for _ in range(s.polish_passes):
            M = self._term_columns(terms, columns, X)
            held = set(terms)
            free = [i for i in pool if exprs[i] not in held]
            parts = _swap_parts(M, F[:, free], y) if free else None  # one projection: swaps and splits
            ranked = _ranked_cells(parts[0]) if parts is not None else []
            singles = [[*terms[:j], exprs[free[f]], *terms[j + 1:]]
                       for j, f, _rss in ranked[: s.polish_tries]]
            # splits never bring in a height feature: a height law is fitted as a whole (its series, or a
            # hub law), and a split there only lengthens the series by whichever power suits the flight's
            # heights (sitl ground effect: h^2 (u1^2 + .. + u4^2) beside the 1/h series, 4 extra terms)
            splits: list[list[sympy.Expr]] = []
            if s.polish_split_width >= 2 and parts is not None:
                motion = np.flatnonzero(~heights[free])
                for j, a, b, _rss in _split_ranking(parts, s.polish_split_width, motion)[: s.polish_tries]:
                    splits.append([*terms[:j], exprs[free[a]], exprs[free[b]], *terms[j + 1:]])
            moves: list[list[sympy.Expr]] = singles + splits
            if occam:
                term_size = [complexity(t) for t in terms]
                smaller = [(j, f) for j, f, _rss in ranked if sizes[free[f]] < term_size[j]]
                for j, f in smaller[: s.polish_tries]:
                    shapes = [*terms[:j], exprs[free[f]], *terms[j + 1:]]
                    if shapes not in moves:
                        moves.append(shapes)
                if len(terms) > 1:
                    for j, _rss in term_removals(M, y)[: s.polish_tries]:
                        moves.append([*terms[:j], *terms[j + 1:]])
                # joins, the splits' inverse: two terms for one pool feature (|vb| + vb^2 |vb| standing for
                # vb^2 on a noisy flight: neither swap alone is better, so the swaps never leave it)
                if s.polish_joins and len(terms) > 2 and free:
                    for j, k, f, _rss in term_merges(M, F[:, free], y)[: s.polish_tries]:
                        shapes = [t for m, t in enumerate(terms) if m not in (j, k)] + [exprs[free[f]]]
                        if shapes not in moves:
                            moves.append(shapes)
            if not moves:
                break
            n_single, n_split = len(singles), len(splits)
            ok = self._refit_moves(moves[:n_single], columns, X, y, Xh, yh, loss, constant)
            split_fits = self._refit_moves(moves[n_single:n_single + n_split], columns, X, y, Xh, yh, loss,
                                           constant)
            ok += split_fits + self._refit_moves(moves[n_single + n_split:], columns, X, y, Xh, yh, loss,
                                                 constant)
            # the model with its constant toggled: a sensor bias (a constant the sparse paths and the GP
            # leave out beside a large term) is a local optimum of the swaps; taken as a grow (the
            # accelerometer's -0.015 m/s^2 on fy of a realistic-sensor flight, pick loss 0.020 -> 0.012)
            toggled = self._refit_moves([terms], columns, X, y, Xh, yh, loss, not constant) \
                if s.polish_constant else []
            ok += toggled
            grow_moves = {id(c) for c in split_fits + toggled}
            if s.polish_rule == "occam":
                # paired t of each move's pick-row losses against the current model's (block means)
                cur = self._pick_rows(current.evaluate(Xh))
                t = {id(c): paired_loss_t(yv, self._pick_rows(c.evaluate(Xh)), cur, loss, s.polish_blocks)
                     for c in ok}
                limit = min(limit, within_tolerance(best_seen, sel, scale))
                # a split (one term for two features) or the constant toggled is taken as a grow: by the
                # standard errors and the pick's tolerance
                grows = {id(c) for c in ok if (s.polish_grow or id(c) in grow_moves)
                         and current.holdout_loss > within_tolerance(c.holdout_loss, sel, scale)}
                better = [c for c in ok if t[id(c)] < -s.polish_z and (
                    c.complexity <= current.complexity or id(c) in grows)]
                simpler = [c for c in ok if c.complexity < current.complexity and t[id(c)] <= s.polish_z
                           and c.holdout_loss <= limit]
            elif s.polish_rule == "tolerance":
                better = [c for c in ok
                          if current.holdout_loss > within_tolerance(c.holdout_loss, sel, scale)]
                limit = min(limit, within_tolerance(best_seen, sel, scale))
                simpler = [c for c in ok if c.complexity < current.complexity and c.holdout_loss <= limit]
            else:  # "margin": a lower pick loss by _better's margin, no simpler moves
                better = [c for c in ok if _better(c, current, scale)]
                simpler = []
            if better:
                current = min(better, key=lambda c: (c.holdout_loss, c.complexity))
            elif simpler:
                current = min(simpler, key=lambda c: (c.complexity, c.holdout_loss))
            else:
                break
            best_seen = min(best_seen, float(current.holdout_loss))
            out.append(current)
            terms = _product_factors(current.expression)
            constant = any(t.is_number for t in sympy.Add.make_args(current.expression))
            if not terms:
                break
        self.stats["polish_swaps"] = len(out)
        return out

    def _pick_rows(self, values: np.ndarray) -> np.ndarray:
        """Values (N,) on the pick rows as the pick's loss sees them: integrated against the pick rows' test
        functions in the weak form, else as they are."""
        weak_h = (self.weak or (None, None))[1]
        return values if weak_h is None else weak_h @ values

    def _term_columns(self, terms: list[sympy.Expr], columns: _Columns, X: np.ndarray) -> np.ndarray:
        """A model's term columns (N, k) on the fit rows X (weak rows when the weak form is on)."""
        return self._on_fit_rows(_lambdify(list(columns.space.primitives), terms)(columns.primitives(X)))

    def _on_fit_rows(self, M: np.ndarray) -> np.ndarray:
        """Point columns (N, k) as the fit rows see them: integrated against the fit rows' test functions in
        the weak form, else as they are."""
        weak = (self.weak or (None, None))[0]
        return M if weak is None else np.asarray(weak @ M)

    def _refit_moves(
        self,
        moves: list[list[sympy.Expr]],
        columns: _Columns,
        X: np.ndarray,
        y: np.ndarray,
        Xh: np.ndarray,
        yh: np.ndarray,
        loss: str,
        constant: bool,
    ) -> list[Candidate]:
        """Each move (a model's term list) refit as the sparse candidates are, with its pick-row loss; the
        ones that pass the pick's rules (identified, no anti-damping) with a finite pick loss."""
        prims = list(columns.space.primitives)
        lag = self._weak_lag()
        fits = (self._linear_candidate(shapes, prims, columns, X, y, loss, lag, constant) for shapes in moves)
        tried = [c for c in fits if c is not None]
        attach_holdout(tried, Xh, yh, loss, (self.weak or (None, None))[1])
        return [c for c in tried if admissible(c, self.selection) and c.holdout_loss is not None
                and np.isfinite(c.holdout_loss)]

    def _no_vif_rule(self) -> SelectionSettings:
        """The pick's rules without the VIF rule (the t rule kept): what the merge repair starts from."""
        return dataclasses.replace(self.selection, max_vif=float("inf"))

    def _merge_repair(
        self,
        start: Candidate,
        columns: _Columns,
        F: np.ndarray,
        y: np.ndarray,
        X: np.ndarray,
        Xh: np.ndarray,
        yh: np.ndarray,
        loss: str,
        scale: float,
    ) -> list[Candidate]:
        """Merge repair of a model past the VIF cap max_vif (DiscoverySettings.polish_merge; the scaled VIF
        rule may pass it on strong evidence, pareto.terms_identified, and the pick then weighs both): two of
        its terms merged into one feature so that the model passes the pick's rules. A term's VIF among
        the terms of one family (one factor times combinations of the rotors) depends on how the family is
        written: closed-loop aero's dwz picked by the t rule alone, wz (u1+u2+u3+u4) + u2 wz + u4 wz + wz
        (coefficients of u2 wz and u4 wz equal), has VIF 199 on wz (u1+u2+u3+u4); the same fit with u2 wz and
        u4 wz merged into wz (u1-u2+u3-u4) (a signed sum of the space, in the span of the two and the sum)
        is the true structure at VIF 36, one parameter fewer. Each step ranks every (pair of terms, feature
        of the grown space) merge by the merged model's least-squares residual on the fit rows (term_merges:
        one QR of the model, one projection of the features; the whole space, not the pool: the pool keeps
        independent columns only, so a combination of two pool features, the merge that rewrites a family,
        is usually not in it), refits the best `polish_tries` as the polish does (_linear_candidate) and
        keeps those that pass the pick's rules (t ratio and VIF), are not worse than `start` on the pick rows
        by more than polish_z standard errors (paired_loss_t) and are within the pick's tolerance of its loss
        (within_tolerance): a merge that drops a direction the fit needs is worse (a tied pair with cancelling
        coefficients fitting what no single feature holds, the targets' errors, keeps it only as the pair),
        and a merged term must pass the t rule, so such a model is still set aside (the repair returns
        nothing and the VIF rule stands: tests/test_discovery_merge.py). Returns [the lowest-loss one kept],
        [] when none is: one merge, not a chain (on sitl ground effect two more steps, each from the merge
        with the lowest VIF, found nothing and cost 4.5 s CPU). The pick weighs what it returns as any
        candidate (and the polish may start from it)."""
        s, sel = self.settings, self.selection
        terms = _product_factors(start.expression)
        if len(terms) < 2 or start.holdout_loss is None or not np.isfinite(start.holdout_loss):
            return []
        exprs = columns.space.expressions
        constant = any(t.is_number for t in sympy.Add.make_args(start.expression))
        yv = self._pick_rows(yh)
        reference = self._pick_rows(start.evaluate(Xh))
        limit = within_tolerance(float(start.holdout_loss), sel, scale)
        M = self._term_columns(terms, columns, X)
        held = set(terms)  # hashed: the ranking holds every (pair, feature) cell of the space
        ranked = ((j, k, f) for j, k, f, _rss in term_merges(M, F, y) if exprs[f] not in held)
        moves = [[t for m, t in enumerate(terms) if m not in (j, k)] + [exprs[f]]
                 for j, k, f in itertools.islice(ranked, s.polish_tries)]
        passing = [c for c in self._refit_moves(moves, columns, X, y, Xh, yh, loss, constant)
                   if c.holdout_loss <= limit
                   and paired_loss_t(yv, self._pick_rows(c.evaluate(Xh)), reference, loss,
                                     s.polish_blocks) <= s.polish_z]
        return [min(passing, key=lambda c: (c.holdout_loss, c.complexity))] if passing else []

    def _linear_candidate(
        self,
        shapes: list[sympy.Expr],
        prims: list[str],
        columns: _Columns,
        X: np.ndarray,
        y: np.ndarray,
        loss: str,
        lag: int | None,
        constant: bool = True,
    ) -> Candidate | None:
        """The model [constant +] sum c_k shapes_k (expressions in the primitive names) fitted to the fit rows
        (X (N,16); y (N,), weak rows when the weak form is on) as the sparse candidates are: least squares,
        then the absolute-error refit; None when a column is not finite."""
        fn = _lambdify(prims, shapes)
        cols = fn(columns.primitives(X))
        if self.weak is not None and self.weak[0] is not None:
            cols = np.asarray(self.weak[0] @ cols)
        theta = np.hstack([np.ones((len(y), 1)), cols])
        if not np.all(np.isfinite(theta)):
            return None
        problem = LeastSquaresProblem(theta, y)
        active = np.ones(theta.shape[1], bool)
        active[0] = constant
        coef = problem.solve(active)
        if loss == "absolute" and theta.shape[1] <= self.sparse.irls_max_terms:
            coef = problem.l1_refit(active, coef, self.sparse.irls_iterations)
        exprs = [sympy.Integer(1), *shapes]
        feats = [Feature(f"x{k}", e, "const" if k == 0 else "polish") for k, e in enumerate(exprs)]
        const, cf = float(coef[0]), np.asarray(coef[1:])
        c = Candidate(
            expression=sparse_expression(feats, coef),
            complexity=sum(complexity(e) + (1 if k == 0 else 2) for k, e in enumerate(exprs)
                           if k > 0 or constant) + 1,
            train_loss=loss_fn(y, theta @ coef, loss),
            engine=f"{self.name}(+polish)",
            predict=lambda X_, cf=cf, k=const: fn(columns.primitives(X_)) @ cf + k,
        )
        if self.identification is not None:
            c.measure = functools.partial(_measure_shapes, self.identification, c.expression)
        else:
            c.weakest_t, c.largest_vif = term_identification(theta[:, active], y, lag, self.noise)
        return c

    def _loss(self, y: np.ndarray, pred: np.ndarray, loss: str) -> float:
        """Training loss of point predictions (N,) against point targets y, in the weak form when it is on."""
        if self.weak is None or self.weak[0] is None:
            return loss_fn(y, pred, loss)
        return loss_fn(self.weak[0] @ y, self.weak[0] @ pred, loss)

    def _weak_lag(self) -> int | None:
        """The fit rows' test-function overlap in weak rows (weak_form.overlap_lag) when the weak form is on,
        else None (point rows: collinearity.effective_rows' AR(1))."""
        if self.weak is None or self.weak[0] is None:
            return None
        return overlap_lag(self.weak[0])

    def _longer_paths(self, best: Candidate | None) -> bool:
        """Lengthen the sparse paths by max_terms / 2 (at most to max_terms_limit) when the round's pick
        (by loss alone) holds as many terms as they reach: the paths, not the rows, ended it; whether they
        were lengthened."""
        s = self.settings
        size = len(self._features.get(id(best), ())) if best is not None else 0
        if size < self._path_terms or self._path_terms >= s.max_terms_limit:
            return False
        self._path_terms = min(self._path_terms + max(s.max_terms // 2, 1), s.max_terms_limit)
        self.stats["path_terms"] = self._path_terms
        return True

    def _sparsify(
        self,
        exprs: list[sympy.Expr],
        groups: list[str],
        theta_pool: np.ndarray,
        keys: list[Any],
        evaluate: Callable[[np.ndarray, np.ndarray], np.ndarray],
        y: np.ndarray,
        loss: str,
        seen: set[frozenset],
        space_indices: np.ndarray | None = None,
        engine: str | None = None,
        weights: np.ndarray | None = None,
        start: list[int] | None = None,
        addable: np.ndarray | None = None,
        means: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
    ) -> list[Candidate]:
        """Every new active set of the sparse paths over (1, pool columns) as a candidate.

        Per pool column: its expression, group, values on the fit rows (theta_pool, N x k) and a hashable
        key; evaluate(X_, js) gives columns js (pool positions) on any rows X_ (N,16). seen: the active sets
        so far, as frozensets of keys with -1 for the constant. space_indices: the columns' indices in the
        feature space (recorded per candidate for the projected and the replacement screening), when they
        are space features. weights: the paths' row weights (robust_weights). start: pool positions of the
        last round's pick, from which one more forward path goes on (the path from no terms re-chooses every
        term on noisy targets and may never reach that model plus the round's new features), adding only the
        pool columns `addable` (bool per pool column; None: any). means(X_, js): columns js's means over
        X_'s rows (each candidate's term_means: its self-feedback slope without evaluating it)."""
        theta = np.hstack([np.ones((len(y), 1)), theta_pool])  # weak rows: V 1 = 1 (weights sum to 1)
        lag = self._weak_lag()  # weak rows: the windows' overlap for the t ratios' effective rows
        problem = LeastSquaresProblem(theta, y, weights)
        exprs = [sympy.Integer(1), *exprs]
        feats = [Feature(f"x{k}", e, "const" if k == 0 else groups[k - 1]) for k, e in enumerate(exprs)]
        nodes = [complexity(e) for e in exprs]
        paths = self.sparse
        if paths.forward_terms != self._path_terms:
            paths = dataclasses.replace(paths, forward_terms=self._path_terms)
        sets = sparse_active_sets(problem, paths, None, [f.group for f in feats], nodes,
                                  None if not start else np.asarray(start, int) + 1,
                                  None if addable is None else np.concatenate(([True], addable)))
        by_size: dict[int, list[tuple[float, int, np.ndarray]]] = {}
        limit = self._path_terms + 1  # + the constant
        for k, active in enumerate(sets):
            if active.sum() > limit:  # larger models are never kept: not solved either
                continue
            key = frozenset(keys[j - 1] if j > 0 else -1 for j in np.flatnonzero(active))
            if key in seen:
                continue
            seen.add(key)
            coef = problem.solve(active)
            r = y - theta @ coef
            rss = float(r @ r) if weights is None else float((weights * r) @ r)
            by_size.setdefault(int(active.sum()), []).append((rss, k, coef))
        kept = [e for size in sorted(by_size) for e in sorted(by_size[size], key=lambda e: e[:2])[:_KEEP]]
        out: list[Candidate] = []
        for _, k, coef in kept:
            active = sets[k]
            if loss == "absolute" and np.count_nonzero(active) <= self.sparse.irls_max_terms:
                coef = problem.l1_refit(active, coef, self.sparse.irls_iterations)
            idx = np.flatnonzero(coef)
            if idx.size == 0:
                continue
            expr = sparse_expression(feats, coef)
            size = sum(nodes[j] + (1 if j == 0 else 2) for j in idx) + (1 if idx.size > 1 else 0)
            c = coef[idx]
            js = np.asarray([j - 1 for j in idx if j > 0], int)
            const = float(coef[0]) if 0 in idx else 0.0
            cf = np.asarray([coef[j] for j in idx if j > 0])
            out.append(
                Candidate(
                    expression=expr,
                    complexity=size,
                    train_loss=loss_fn(y, theta[:, idx] @ c, loss),
                    engine=engine or self.name,
                    predict=lambda X_, js=js, cf=cf, k=const: evaluate(X_, js) @ cf + k,
                    term_means=None if means is None else (lambda X_, js=js: means(X_, js), cf),
                )
            )
            out[-1].measure = functools.partial(_measure_terms, theta, idx, y, lag, self.noise) \
                if self.identification is None else \
                functools.partial(_measure_shapes, self.identification, out[-1].expression)
            if space_indices is not None:
                self._features[id(out[-1])] = space_indices[js]
        return out

    def _operon(
        self,
        best: Candidate,
        columns: _Columns,
        X: np.ndarray,
        y: np.ndarray,
        Xh: np.ndarray,
        yh: np.ndarray,
        seed: int,
        loss: str,
        generations: int,
    ) -> list[Candidate]:
        """Genetic programming on best's residual, seeded with the primitives and best's features.

        In the weak form the GP sees the point residual (pyoperon fits samples); its candidates' losses are
        then weak ones, as every other candidate's."""
        try:
            from pyoperon.sklearn import SymbolicRegressor
        except ImportError as exc:
            raise UserError(f"the discovery engine needs pyoperon ({exc})",
                            hint="pip install pyoperon") from None
        s = self.settings
        prims = list(columns.space.primitives)
        # the ground plane's normal (gx, gy) only inside the features that hold it (a height law's gradient)
        own = [k for k, n in enumerate(prims) if not PRIMITIVES[n].ground_normal]
        # a hub law is no seed: its expression is large and GP products of it would be expanded term by term
        laws = {law.expression() for law in columns.space.laws}
        seeds = [f for f in _product_factors(best.expression) if f not in laws]
        names = [prims[k] for k in own] + [f"s{k}" for k in range(len(seeds))]
        mapping: dict[str, sympy.Expr] = {prims[k]: PRIMITIVE_SYMBOLS[prims[k]] for k in own}
        mapping.update({f"s{k}": e for k, e in enumerate(seeds)})
        seed_fn = _lambdify(prims, seeds)
        P = columns.primitives(X)
        rows = gp_rows(len(X), s.operon_rows)
        Pg = P[rows]
        inputs = np.hstack([Pg[:, own], seed_fn(Pg)]) if seeds else Pg[:, own]
        residual = y[rows] - best.evaluate(X[rows])
        reg = SymbolicRegressor(
            allowed_symbols="add,sub,mul,div,constant,variable",
            objectives=["r2", "length"],
            optimizer_iterations=s.operon_optimizer_iterations,
            population_size=s.operon_population,
            generations=generations,
            max_length=s.operon_max_length,
            max_depth=8,
            n_threads=s.operon_threads,
            random_state=int(seed),
        )
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            reg.fit(inputs, residual)
        self.stats["operon_generations"] = int(reg.stats_.get("generations", generations))
        self.stats["operon_front"] = len(reg.pareto_front_)
        out: list[Candidate] = []
        seen: set[str] = set()
        extras: list[sympy.Expr] = []
        for point in reg.pareto_front_:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # "Model contains no variables" for a constant
                text = reg.get_model_string(point["tree"], _PRECISION, names).replace("^", "**")
            try:
                extra = parse_expression(text, mapping)
            except (ExpressionError, RecursionError):
                continue
            if str(extra) in seen or extra.is_number:
                continue
            seen.add(str(extra))
            fn = _lambdify(prims, [extra])
            expr = sympy.Add(best.expression, extra, evaluate=False)

            def predict(X_: np.ndarray, fn: Callable[[np.ndarray], np.ndarray] = fn) -> np.ndarray:
                return best.evaluate(X_) + fn(columns.primitives(X_))[:, 0]

            out.append(
                Candidate(
                    expression=expr,
                    complexity=best.complexity + complexity(extra) + 1,
                    train_loss=self._loss(y, predict(X), loss),
                    engine=f"{self.name}(+operon)",
                    predict=predict,
                )
            )
            shapes = term_shapes(expr)  # every additive term of the sum with its own coefficient
            if shapes and self.identification is not None:
                out[-1].measure = functools.partial(self.identification, shapes)
            elif shapes:
                out[-1].weakest_t, out[-1].largest_vif = term_identification(_lambdify(prims, shapes)(P), y)
            extras.append(extra)
        return self._refit_expanded(best, extras, prims, columns, X, y, loss) or out

    def _refit_expanded(
        self,
        best: Candidate,
        extras: list[sympy.Expr],
        prims: list[str],
        columns: _Columns,
        X: np.ndarray,
        y: np.ndarray,
        loss: str,
    ) -> list[Candidate]:
        """The GP front's expressions back in the sparse selection as their expanded terms: each expanded
        into its additive terms (coefficients dropped), which join the picked model's features in one more
        sparse fit (least squares, the sparse paths, the pick's rules), so a GP product is refit and pruned
        term by term, and a candidate costs the complexity of the terms it keeps, not of one opaque tree.
        A term that is a combination of the others (u1*ub beside ub*(u1+u2+u3+u4) ...) is left out as in the
        pool, and so is a front member expanding to more terms than 3 x max_terms, and a term with a pole
        inside the data (pole_in_data); [] when no term is new (the caller then keeps the GP candidates as
        they are). y: point targets (N,) of the fit rows X."""
        base = _product_factors(best.expression)
        shapes = list(base)
        P = columns.primitives(X)
        for extra in extras:
            try:
                new = [t for t in term_shapes(sympy.expand(extra)) if t != 1 and t not in shapes]
            except (RecursionError, TypeError, ValueError):
                continue
            new = [t for t in new if not pole_in_data(t, prims, P)]
            if len(shapes) + len(new) <= 3 * self.settings.max_terms:
                shapes += new
        if len(shapes) == len(base):
            return []
        cols = _lambdify(prims, shapes)(columns.primitives(X))
        basis = _Basis(len(X))  # the picked model's features first; a GP term only where independent of them
        accepted = set(basis.add_first(cols, range(cols.shape[1])))  # never one with a NaN or inf value
        finite = np.array([j in accepted for j in range(cols.shape[1])])
        shapes = [e for e, ok in zip(shapes, finite, strict=True) if ok]
        fn = _lambdify(prims, shapes)

        def evaluate(X_: np.ndarray, js: np.ndarray) -> np.ndarray:
            return fn(columns.primitives(X_))[:, js]

        theta, target = cols[:, finite], y
        if self.weak is not None and self.weak[0] is not None:
            theta, target = np.asarray(self.weak[0] @ theta), self.weak[0] @ y
        groups = ["picked" if e in base else "operon" for e in shapes]
        return self._sparsify(shapes, groups, theta, [str(e) for e in shapes], evaluate, target, loss, set(),
                              engine=f"{self.name}(+operon)")


_LAST_SPACE: dict[str, Any] = {}  # the last training data's feature space and matrix (one entry)


def gp_rows(n: int, limit: int) -> np.ndarray:
    """Indices of at most `limit` of n rows, evenly strided from the first (all n when limit is 0 or >= n)."""
    if limit <= 0 or n <= limit:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, limit).round().astype(int))


def _measure_terms(theta: np.ndarray, idx: np.ndarray, y: np.ndarray, lag: int | None,
                   noise: Whitener | None = None) -> tuple[float, float]:
    """(weakest t ratio, largest VIF) of the columns idx of theta (N,p) fitting y (N,): a sparse candidate's
    deferred measure (Candidate.measure)."""
    return term_identification(theta[:, idx], y, lag, noise)


def _measure_shapes(identification: Callable[[list[sympy.Expr]], tuple[float, float]],
                    expression: sympy.Expr) -> tuple[float, float]:
    """(weakest t ratio, largest VIF) of an expression's additive terms on the rows `identification`
    measures on (DiscoveryEngine.identification)."""
    return identification(term_shapes(expression))


def _rows_key(X: np.ndarray) -> str:
    """A digest of a training flight's rows (what the space and the hub offsets are cached under)."""
    return hashlib.sha256(np.ascontiguousarray(X).tobytes()).hexdigest()


_KEEP = 3  # candidates kept per model size (number of terms): the best by training residual


class _Basis:
    """An orthonormal basis of the pool's columns (and the constant), to keep only independent features.

    Candidates are tested in order, in blocks: a block is projected out of the basis as it stood with one
    matrix product (twice: classical Gram-Schmidt loses orthogonality once), then each of its columns out of
    the block's columns accepted before it; mathematically the column-by-column test, at BLAS-3 speed. The
    basis lives in a preallocated buffer (grown by doubling) rather than being copied on every addition.
    The basis only grows, so a column found dependent on it stays dependent: it is not tested again (the
    screening's later rounds offer hundreds of features the pool already spans)."""

    _BLOCK = 32  # candidates projected together

    def __init__(self, n: int, tol: float = 1e-8):
        self._q = np.empty((n, 64))
        self._q[:, 0] = 1.0 / np.sqrt(n)
        self.k = 1  # columns in use
        self.tol = tol
        self._dependent: set[int] = set()  # column indices found dependent on the basis
        self._coordinates: dict[int, np.ndarray] = {}  # coordinates(): column index -> Q^T its unit column

    def coordinates(self, F: np.ndarray, indices: Sequence[int]) -> np.ndarray:
        """The coordinates in the basis (k, len(indices)) of each column F[:, i] scaled to unit norm (-1: the
        constant column); kept per column and extended as the basis grows, so that each round computes only
        the new columns' and the new basis vectors' (the rounds append columns to F, never change one)."""
        k, q = self.k, self.q
        if not len(indices):
            return np.zeros((k, 0))
        todo: dict[int, list[int]] = {}  # columns by how many of their coordinates are kept
        for i in indices:
            have = self._coordinates.get(int(i))
            done = 0 if have is None else len(have)
            if done < k:
                todo.setdefault(done, []).append(int(i))
        for done, cols in todo.items():
            unit = np.column_stack([q[:, 0] if i == -1 else F[:, i] for i in cols])
            more = q[:, done:].T @ (unit / np.linalg.norm(unit, axis=0))
            for m, i in enumerate(cols):
                have = self._coordinates.get(i)
                self._coordinates[i] = more[:, m] if have is None else np.concatenate([have, more[:, m]])
        return np.column_stack([self._coordinates[int(i)] for i in indices])

    @property
    def q(self) -> np.ndarray:
        """The basis (N, k), orthonormal columns."""
        return self._q[:, : self.k]

    def add_first(self, F: np.ndarray, indices: Sequence[int], limit: int | None = None) -> list[int]:
        """Add, in order, each column F[:, i] (i in indices) that is not (numerically) a combination of the
        basis and the columns added before it, until `limit` are added; the indices added."""
        added: list[int] = []
        indices = np.asarray([i for i in indices if int(i) not in self._dependent], dtype=int)
        for start in range(0, len(indices), self._BLOCK):
            if limit is not None and len(added) >= limit:
                break
            idx = indices[start : start + self._BLOCK]
            block = F[:, idx]
            with np.errstate(all="ignore"):
                norms = np.sqrt(np.sum(block * block, axis=0))
            usable = np.isfinite(norms) & (norms > 0.0)
            idx, v = idx[usable], block[:, usable] / norms[usable]
            old = self.q
            for _ in range(2):
                v = v - old @ (old.T @ v)
            k0 = self.k
            for j in range(len(idx)):
                if limit is not None and len(added) >= limit:
                    break
                col = v[:, j]
                if self.k > k0:  # out of this block's columns accepted before it
                    mine = self._q[:, k0 : self.k]
                    for _ in range(2):
                        col = col - mine @ (mine.T @ col)
                rest = float(np.linalg.norm(col))
                if rest <= self.tol:
                    self._dependent.add(int(idx[j]))
                    continue
                self._append(col / rest)
                added.append(int(idx[j]))
        return added

    def _append(self, col: np.ndarray) -> None:
        if self.k == self._q.shape[1]:
            grown = np.empty((self._q.shape[0], 2 * self.k))
            grown[:, : self.k] = self._q
            self._q = grown
        self._q[:, self.k] = col
        self.k += 1


def _better(new: Candidate, old: Candidate, scale: float, margin: float = 1e-3) -> bool:
    """True when new's held-out loss is below old's by more than `margin` of it and more than rounding
    (1e-9 of the held-out target's spread `scale`): a round that helped."""
    a, b = new.holdout_loss, old.holdout_loss
    if a is None or b is None or not np.isfinite(a):
        return False
    return not np.isfinite(b) or a < b * (1.0 - margin) - 1e-9 * scale


def _exact(c: Candidate, scale: float) -> bool:
    """True when c's held-out loss is at rounding level (1e-9 of the held-out target's spread, as in
    _better): no later round can be better, so none is run."""
    return c.holdout_loss is not None and bool(c.holdout_loss <= 1e-9 * scale)


def _standardized(F: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Columns centred and scaled to unit RMS; unusable columns (constant, not finite) all NaN; written
    into `out` (F's shape) when given."""
    with np.errstate(all="ignore"):
        fc = F - F.mean(axis=0)
        std = np.sqrt(np.mean(fc * fc, axis=0))
        ok = (std > 1e-12 * np.maximum(np.abs(F).max(axis=0), 1e-300)) & np.all(np.isfinite(F), axis=0)
        if out is None:
            return np.where(ok, fc / np.where(ok, std, 1.0), np.nan)
        np.divide(fc, np.where(ok, std, 1.0), out=out)
        out[:, ~ok] = np.nan
        return out


def _standardized_buffer(F: np.ndarray, room: int) -> ColumnBuffer:
    """F standardized (_standardized) into a new ColumnBuffer with room for `room` more columns."""
    out = ColumnBuffer(F.shape[0], F.shape[1], room)
    _standardized(F, out=out.view())
    return out


def _screen_scores(Z: np.ndarray, r: np.ndarray) -> np.ndarray:
    """|correlation| of each standardized column of Z with r (sure independence screening); -inf where
    a column is unusable."""
    rc = r - r.mean()
    rs = float(np.sqrt(np.mean(rc * rc)))
    with np.errstate(all="ignore"):
        scores = np.abs(np.nan_to_num(Z.T @ rc, nan=np.nan)) / (len(r) * (rs if rs > 0 else 1.0))
    return np.where(np.isfinite(scores), scores, -np.inf)


def _projected_scores(
    Z: np.ndarray, r: np.ndarray, model: np.ndarray, floor: float = 1e-5, prepared: tuple | None = None
) -> np.ndarray:
    """|correlation| of each standardized column of Z (N,M) with the residual r (N,), both taken orthogonal
    to the current model's columns `model` (N,k) and the constant: what each feature adds to the model
    against what the model leaves unexplained (orthogonal matching pursuit's criterion). Plain screening
    ranks a feature nearly collinear with a model term (wz*(u1+..+u4) beside wz when the rotor sum varies
    by 5 %) by the part the model already explains, so the residual it would remove never brings it in.
    -inf where a column is unusable or adds less than `floor` of its own spread (numerically in the span).
    prepared: (Z with NaN as 0, its columns' sums of squares, its usable columns), computed here if None."""
    if model.shape[1] == 0:
        return _screen_scores(Z, r)
    basis = np.hstack([np.ones((len(r), 1)), model])
    basis = basis[:, np.all(np.isfinite(basis), axis=0)]
    q, rr = np.linalg.qr(basis)
    q = q[:, np.abs(np.diag(rr)) > 1e-10 * max(float(np.abs(np.diag(rr)).max()), 1e-300)]
    r_perp = r - q @ (q.T @ r)
    rs = float(np.linalg.norm(r_perp))
    if prepared is None:
        Zf = np.nan_to_num(Z, nan=0.0)
        prepared = (Zf, np.sum(Zf * Zf, axis=0), np.all(np.isfinite(Z[:1]), axis=0))
    Zf, zz, finite = prepared
    with np.errstate(all="ignore"):
        along = q.T @ Zf
        perp2 = zz - np.sum(along * along, axis=0)
        usable = finite & (perp2 > (floor**2) * len(r))
        scores = np.abs(r_perp @ Zf) / ((rs if rs > 0 else 1.0) * np.sqrt(np.where(usable, perp2, 1.0)))
    return np.where(usable & np.isfinite(scores), scores, -np.inf)


def inverse_notes(s: DiscoverySettings, X: np.ndarray) -> list[str]:
    """Identifiability notes for the positive primitives (the height, m) that get no 1/x^k features because
    the fit rows X (N,16) come near zero on their own scale (min < median / inverse_span,
    feature_space.grow_unary): a law that falls off with x (ground effect) is not identified from such a
    flight, which passes near zero (a take-off) but spends its rows far from it; what would identify it."""
    if "inv" not in s.operators:
        return []
    P = primitive_matrix(X, s.primitives)
    out = []
    for k, name in enumerate(s.primitives):
        x = P[:, k]
        if not PRIMITIVES[name].positive or not len(x) or not np.all(x > 0):
            continue
        low, median = float(x.min()), float(np.median(x))
        if low * s.inverse_span >= median:
            continue
        near = float(np.mean(x * s.inverse_span < median))  # the rows where a 1/x law would be resolved
        out.append(f"{name}: no 1/{name}^k features (its lowest value on the fit rows, {low:.3g}, is below "
                   f"its median {median:.3g} / {s.inverse_span:g}: a few rows would own a law in 1/{name});"
                   f" a law that falls off with {name} (ground effect) is not identified from this flight "
                   f"({near:.1%} of its rows below median / {s.inverse_span:g}); to identify it, fly longer "
                   f"within a factor {s.inverse_span:g} of the lowest {name} (a low hover near the ground)")
    return out


def pole_in_data(term: sympy.Expr, prims: Sequence[str], P: np.ndarray) -> bool:
    """True when a term (primitive names) has a pole inside the data: its denominator takes both signs or
    is zero on some row of P (N, n_primitives), so the term is unbounded between the rows. The feature
    space never builds 1/x for such an x (feature_space.grow_unary); genetic programming divides freely,
    and a quotient by a quantity crossing zero (|ub|/(h^2 vb)) fits a handful of rows near the pole with a
    coefficient of 1e-20: no physical law (a force or moment) is unbounded inside the flown envelope."""
    _, den = sympy.fraction(sympy.together(term))
    if den.is_number:
        return False
    missing = [s for s in den.free_symbols if str(s) not in prims]
    if missing:
        return False
    values = _lambdify(list(prims), [den])(P)[:, 0]
    finite = values[np.isfinite(values)]
    return bool(len(finite) < len(values) or np.any(finite == 0.0)
                or (np.any(finite < 0.0) and np.any(finite > 0.0)))


def _swap_in_combinations(
    F: np.ndarray,
    pool: list[int],
    features: Sequence[int],
    fixed: set[int],
    scores: np.ndarray,
    model_t: dict[int, float],
    tol: float = 1e-8,
    member_tol: float = 1e-6,
    basis: _Basis | None = None,
) -> list[int]:
    """Each of `features` (columns of F (N,M)) that is a linear combination of two or more pool columns (and
    the constant) takes, in `pool` (changed in place), the place of one of them: the pool spans the same
    space and stays independent, but the combination is now one term. The pool keeps independent columns
    only, in the order they came, so the first of several exactly dependent features blocks the others:
    with u2 wz, u4 wz and wz (u1 - u2 + u3 - u4) in, wz (u1 + u2 + u3 + u4) = wz (u1 - u2 + u3 - u4) +
    2 u2 wz + 2 u4 wz is left out, and a target with a small common part c wz (u1 + u2 + u3 + u4) needs two
    terms of coefficient 2c for it, each below the pick's t ratio (fang-chen-aero's dwx: rotor drag of the
    yaw rate with the CG aft of the rotors' centre). The member replaced is not in `fixed` (rung 1, always
    in): one outside the current model first, the lowest `scores` (per column of F: what it adds to the
    model against the residual, _projected_scores), else the model's term with the lowest t ratio
    (`model_t`: the term the flight pins down least, the one a shared part of the others is likely split
    into; the model stays in the pool's span, and rewritten with the combination the split part is one
    term the sparse paths can keep and the rest near zero). The combination (unique: the pool is
    independent) is the least-squares one over the pool's unit columns, its members those weighing more
    than `member_tol`; a feature whose rest exceeds `tol` of its norm is independent and left alone (only
    features the pool rejected come here, a few a round). basis: the rounds' basis (_Basis: it spans the
    pool and the constant): the least squares is then solved on the columns' coordinates in it
    (_Basis.coordinates, kept from round to round), not on the N rows. Returns the features swapped in."""
    swapped: list[int] = []
    if not features or not pool:
        return swapped
    n = F.shape[0]
    pending: list[tuple[int, np.ndarray]] = []
    for f in features:
        size = float(np.linalg.norm(F[:, f]))
        if f not in pool and np.isfinite(size) and size > 0.0:
            pending.append((f, F[:, f] / size))
    if not pending:
        return swapped
    if basis is not None:
        # |A c - v|^2 = |T c - Q^T v|^2 + |v - Q Q^T v|^2 for A = Q T, Q orthonormal
        A = np.hstack([basis.coordinates(F, [-1]), basis.coordinates(F, pool)])
    else:
        cols = F[:, pool]
        A = np.hstack([np.full((n, 1), 1.0 / np.sqrt(n)), cols / np.linalg.norm(cols, axis=0)])
    while pending:
        # one factorisation for every pending feature; after a swap the pool changed, so the rest again
        V = np.column_stack([v for _, v in pending])
        if basis is not None:
            inside = basis.q.T @ V
            coefs, rests = lstsq_by_qr(A, inside)
            rests = np.hypot(rests, np.linalg.norm(V - basis.q @ inside, axis=0))
        else:
            coefs, rests = lstsq_by_qr(A, V)
        for j, (f, v) in enumerate(pending):
            if f in pool or not rests[j] <= tol:
                continue
            members = [pool[i] for i in np.flatnonzero(np.abs(coefs[1:, j]) > member_tol)]
            free = [i for i in members if i not in fixed]
            if len(members) < 2 or not free:
                continue
            out = min(free, key=lambda i: (1, model_t[i]) if i in model_t else
                      (0, scores[i] if np.isfinite(scores[i]) else -np.inf))
            k = pool.index(out)
            pool[k] = f
            A[:, k + 1] = v if basis is None else basis.coordinates(F, [f])[:, 0]
            swapped.append(f)
            pending = pending[j + 1:]
            break
        else:
            pending = []
    return swapped


def term_substitutions(
    M: np.ndarray, C: np.ndarray, y: np.ndarray, tol: float = 1e-10
) -> list[tuple[int, int, float]]:
    """Every swap of one model term for one candidate feature, ranked by the swapped model's least-squares
    residual sum of squares on y (N,) (with a constant): [(term j, candidate f, RSS)], lowest first (stable).
    M (N,k): the model's term columns; C (N,m): the candidates'. One QR of the model and one projection of
    the candidates serve every swap: with u_j the unit direction of term j orthogonal to the other terms
    (a column of Q R^-T), removing j adds (u_j.y)^2 to the RSS and u_j (u_j.c) to each candidate's part
    outside the model, so RSS(j -> f) = RSS + (u_j.y)^2 - (r.c_perp + (u_j.y)(u_j.c))^2 / (|c_perp|^2 +
    (u_j.c)^2), r the model's residual. A candidate (numerically) inside the model's span (a copy of a
    term, or a combination of them: no new direction), or not finite, is left out. Units: y's squared."""
    parts = _swap_parts(M, C, y, tol)
    if parts is None:
        return []
    return _ranked_cells(parts[0])


def _ranked_cells(new: np.ndarray) -> list[tuple[int, int, float]]:
    """The finite cells of an RSS table (rows: moves of the model's terms, columns: candidates) as
    (row, column, RSS), lowest first (stable)."""
    out = []
    for idx in np.argsort(new, axis=None, kind="stable"):
        j, f = divmod(int(idx), new.shape[1])
        if not np.isfinite(new[j, f]):
            break
        out.append((j, f, float(new[j, f])))
    return out


def term_splits(
    M: np.ndarray, C: np.ndarray, y: np.ndarray, width: int, tol: float = 1e-10
) -> list[tuple[int, int, int, float]]:
    """Swaps of one model term for two candidate features, ranked by the model's least-squares RSS on y:
    [(term j, candidate a, candidate b (a < b), RSS)], lowest first (stable), for the pairs among each
    term's `width` best single swaps (term_substitutions). With r_j = r + u_j (u_j.y) the residual without
    term j and c~ = c_perp + u_j (u_j.c) each candidate's part outside the model without j, the pair's RSS
    is |r_j|^2 - g' G^-1 g, g = (c~.r_j) and G = (c~_a.c~_b): one Gram matrix of the width best per term."""
    parts = _swap_parts(M, C, y, tol)
    if parts is None:
        return []
    return _split_ranking(parts, width, np.arange(C.shape[1]), tol)


def _split_ranking(parts: tuple, width: int, cols: np.ndarray, tol: float = 1e-10) -> list:
    """term_splits from _swap_parts' quantities, the pairs drawn from the candidate columns `cols` only."""
    new, rss, uy, uc, Cp, num0 = parts
    out: list[tuple[int, int, int, float]] = []
    if len(cols) < 2:
        return out
    for j in range(new.shape[0]):
        top = cols[np.argsort(new[j, cols], kind="stable")[:width]]
        top = top[np.isfinite(new[j, top])]
        if len(top) < 2:
            continue
        g = num0[top] + uy[j] * uc[j, top]
        G = Cp[:, top].T @ Cp[:, top] + np.outer(uc[j, top], uc[j, top])
        base = rss + uy[j] ** 2
        for a in range(len(top)):
            for b in range(a + 1, len(top)):
                sub = G[np.ix_([a, b], [a, b])]
                det = sub[0, 0] * sub[1, 1] - sub[0, 1] ** 2
                if not det > tol * sub[0, 0] * sub[1, 1]:
                    continue  # the two are (nearly) one direction
                ga, gb = g[a], g[b]
                gain = (sub[1, 1] * ga * ga - 2.0 * sub[0, 1] * ga * gb + sub[0, 0] * gb * gb) / det
                fa, fb = sorted((int(top[a]), int(top[b])))
                out.append((j, fa, fb, float(base - gain)))
    out.sort(key=lambda item: item[3])
    return out


def _swap_parts(M: np.ndarray, C: np.ndarray, y: np.ndarray, tol: float = 1e-10) -> tuple | None:
    """term_substitutions' quantities: (RSS per swap (k, m), the model's RSS, u_j.y (k,), u_j.c (k, m),
    the candidates' parts outside the model (N, m), r.c_perp (m,)); None for an empty or singular model."""
    n, k = M.shape
    A = np.hstack([np.ones((n, 1)), M])
    q, r_ = np.linalg.qr(A)
    if k == 0 or np.min(np.abs(np.diag(r_))) <= 1e-12 * np.max(np.abs(np.diag(r_))):
        return None
    U = q @ np.linalg.inv(r_).T[:, 1:]  # column j: orthogonal to every other column of A
    U /= np.linalg.norm(U, axis=0)
    finite = np.all(np.isfinite(C), axis=0)
    C = np.where(finite, C, 0.0)
    resid = y - q @ (q.T @ y)
    rss = float(resid @ resid)
    Cp = C - q @ (q.T @ C)
    num0 = resid @ Cp  # (m,)
    den0 = np.sum(Cp * Cp, axis=0)
    uy = U.T @ y  # (k,)
    uc = U.T @ C  # (k, m)
    num = num0[None, :] + uy[:, None] * uc
    den = den0[None, :] + uc * uc
    size = np.sum(C * C, axis=0)
    usable = (finite & (den0 > tol * np.maximum(size, 1e-300)))[None, :] & (den > 0.0)
    with np.errstate(all="ignore"):
        new = rss + (uy * uy)[:, None] - np.where(usable, num * num / np.where(usable, den, 1.0), 0.0)
    new = np.where(usable, new, np.inf)
    return new, rss, uy, uc, Cp, num0


def term_merges(
    M: np.ndarray, C: np.ndarray, y: np.ndarray, tol: float = 1e-10, block: int = 1024
) -> list[tuple[int, int, int, float]]:
    """Every merge of two model terms into one candidate feature, ranked by the merged model's least-squares
    residual sum of squares on y (N,) (with a constant): [(term j, term k (j < k), candidate f, RSS)], lowest
    first (stable). M (N,k): the model's term columns; C (N,m): the candidates'. One QR of the model and one
    projection of the candidates serve every merge: the columns of Q R^-T (A = [1, M] = Q R) are the dual
    directions, each orthogonal to every other column of A, so the directions of terms j and k (orthonormal
    W in Q's coordinates: a 2 x 2 QR per pair), span what the model loses without them; removing both adds
    |W.y|^2 to the RSS and W (W.c) to each candidate's part outside the model, so RSS(j, k -> f) = RSS +
    |W.y|^2 - (r.c_perp + (W.y).(W.c))^2 / (|c_perp|^2 + |W.c|^2), r the model's residual (term_substitutions
    for one term). A candidate inside the span of the model without j and k (no new direction), or not
    finite, is left out; one inside the full model's span is kept (a combination of j and k: the merge that
    rewrites a family). Empty with fewer than two terms or dependent columns. The candidates are taken
    `block` columns at a time (memory). Units: y's squared."""
    n, k = M.shape
    if k < 2 or not np.all(np.isfinite(M)):
        return []
    q, r_ = np.linalg.qr(np.hstack([np.ones((n, 1)), M]))
    if np.min(np.abs(np.diag(r_))) <= 1e-12 * np.max(np.abs(np.diag(r_))):
        return []
    B = np.linalg.inv(r_).T  # the dual directions in q's coordinates
    qy = q.T @ y
    resid = y - q @ qy
    rss = float(resid @ resid)
    pairs = [(j, l) for j in range(k) for l in range(j + 1, k)]
    W = [np.linalg.qr(B[:, [j + 1, l + 1]])[0] for j, l in pairs]
    wy = np.stack([w.T @ qy for w in W])  # (pairs, 2)
    new = np.full((len(pairs), C.shape[1]), np.inf)
    for start in range(0, C.shape[1], block):  # bounded memory over a large feature space
        part = C[:, start : start + block]
        finite = np.all(np.isfinite(part), axis=0)
        part = np.where(finite, part, 0.0)
        qC = q.T @ part
        Cp = part - q @ qC
        num0 = resid @ Cp
        den0 = np.sum(Cp * Cp, axis=0)
        size = np.sum(part * part, axis=0)
        for p, w in enumerate(W):
            wc = w.T @ qC
            num = num0 + wy[p] @ wc
            den = den0 + np.sum(wc * wc, axis=0)
            usable = finite & (den > tol * np.maximum(size, 1e-300))
            with np.errstate(all="ignore"):
                new[p, start : start + part.shape[1]] = np.where(
                    usable, rss + float(wy[p] @ wy[p]) - num * num / np.where(usable, den, 1.0), np.inf)
    return [(pairs[p][0], pairs[p][1], f, rss) for p, f, rss in _ranked_cells(new)]


def term_removals(M: np.ndarray, y: np.ndarray) -> list[tuple[int, float]]:
    """Every removal of one model term, ranked by the reduced model's least-squares residual sum of squares on
    y (N,) (with a constant): [(term j, RSS)], lowest first (stable). M (N,k): the model's term columns.
    One QR serves every removal: with u_j the unit direction of term j orthogonal to the other columns,
    removing j adds (u_j.y)^2 to the RSS (term_substitutions). Empty when the columns are dependent."""
    n, k = M.shape
    if k == 0 or not np.all(np.isfinite(M)):
        return []
    q, r_ = np.linalg.qr(np.hstack([np.ones((n, 1)), M]))
    if np.min(np.abs(np.diag(r_))) <= 1e-12 * np.max(np.abs(np.diag(r_))):
        return []
    U = q @ np.linalg.inv(r_).T[:, 1:]
    U /= np.linalg.norm(U, axis=0)
    resid = y - q @ (q.T @ y)
    rss = float(resid @ resid) + (U.T @ y) ** 2
    return [(int(j), float(rss[j])) for j in np.argsort(rss, kind="stable")]


def _model_t(F: np.ndarray, terms: np.ndarray, y: np.ndarray) -> dict[int, float]:
    """Each model term's t ratio (collinearity.term_t_ratios: least squares with a constant, AR(1)-corrected
    sample size) on columns F[:, terms] (N,k) against y (N,); NaN where it cannot be measured."""
    terms = [int(i) for i in terms]
    if not terms:
        return {}
    t, _ = term_t_ratios(np.hstack([np.ones((len(y), 1)), F[:, terms]]), y)
    if t is None:
        return {}
    return {i: float(tk) if np.isfinite(tk) else float("nan") for i, tk in zip(terms, t[1:], strict=True)}


def _product_factors(expr: sympy.Expr) -> list[sympy.Expr]:
    """The non-constant features of a sum of coefficient x feature (the GP's seed inputs)."""
    out: list[sympy.Expr] = []
    for term in sympy.Add.make_args(expr):
        factors = [f for f in sympy.Mul.make_args(term) if not f.is_number]
        if factors:
            feature = sympy.Mul(*factors)
            if feature not in out:
                out.append(feature)
    return out


def _lambdify(prims: list[str], exprs: list[sympy.Expr]) -> Callable[[np.ndarray], np.ndarray]:
    """P (N, n_primitives) -> (N, len(exprs)) for expressions in the primitive names."""
    names = tuple(prims)
    fns = [(e, _expression_fn(names, e)) for e in exprs]

    def matrix(P: np.ndarray) -> np.ndarray:
        # each expression's column once per primitive matrix (identification.rows_cache): the polish refits
        # hundreds of term lists that share all but one term, and a hub law's columns are large expressions
        # (evaluated anew each time, closed-loop aero's identify took 123 s where it takes 90 s now)
        args: list[np.ndarray] = []

        def column(fn: Callable[..., np.ndarray]) -> np.ndarray:
            if not args:
                args.extend(P[:, k] for k in range(P.shape[1]))
            with np.errstate(all="ignore"):
                return np.broadcast_to(np.asarray(fn(*args), float), (P.shape[0],))

        out = np.empty((P.shape[0], len(fns)))
        for j, (e, fn) in enumerate(fns):
            out[:, j] = cached(P, (names, e), lambda fn=fn: column(fn))
        return out

    return matrix


@functools.lru_cache(maxsize=8192)
def _expression_fn(prims: tuple[str, ...], expr: sympy.Expr) -> Callable[..., np.ndarray]:
    """One expression compiled once (the polish and the merge repair refit the same terms in many term
    lists; a hub law is a large expression)."""
    return sympy.lambdify([PRIMITIVE_SYMBOLS[n] for n in prims], expr, modules="numpy")
