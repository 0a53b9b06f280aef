"""Blocked K-fold cross-validation over the fit and pick rows: the final pick's evidence when
SelectionSettings.cv_folds > 1 (identification.identify).

The single pick block is a fifth of the flight: on a noisy flight two structures a few per cent apart
swap order from one block to another (realistic-sensor fang-chen-aero's fy: u_i wz against u_i^2 wz,
README session 14). Here every candidate's terms are refit K times, each time without one of K contiguous
blocks of the fit and pick rows and without `gap` rows on either side of it (the rows whose derivative
windows or weak-form test functions overlap the held-out block's), and scored on the block left out; the
candidate's held-out loss is the loss of those held-out predictions over all rows. Each prediction comes
from a fit that never saw its row, so the pick still chooses on data its fits did not use; the
validation rows are in no fold.

The refits are least squares (the absolute-error refit is left out: K refits per candidate, and the
ranking, not the coefficients, is what the folds are for); the chosen structure is then refit once on
all the folds (identification.refit).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import numpy as np
import sympy
from scipy import sparse

from identification.body_frame import expression_columns
from identification.candidate import Candidate
from identification.collinearity import CentredPool, term_identification, term_shapes
from identification.metrics import loss as loss_fn
from identification.sparse import single_threaded_blas
from identification.weak_noise import Whitener

MIN_BLOCK_GAPS = 4  # a held-out block is at least this many gaps long (fewer blocks per fold if need be)
Part = tuple[np.ndarray, np.ndarray, "sparse.spmatrix | None", int]  # X (N,16), y (N,), weak op, gap rows


class FoldedRows:
    """The fit and pick rows (point or weak rows) cut into K contiguous folds, with each term's values on
    them computed once (candidates of one target share most terms)."""

    def __init__(self, parts: Sequence[Part], folds: int, blocks_per_fold: int = 1,
                 fit_noise: Whitener | None = None, all_noise: Whitener | None = None,
                 identify_on_all: bool = False):
        """parts: (X (N,16), y (N,) in the target's unit, the weak operator of those rows or None, the gap
        in rows either side of a held-out block); folds >= 2; the rows are cut into folds x blocks_per_fold
        contiguous blocks, dealt to the folds in turn (fold k holds blocks k, k + folds, ...); fewer blocks
        per fold where a block would be shorter than MIN_BLOCK_GAPS gaps; `usable` False when even one
        block per fold would be (too few rows: the caller picks on the pick rows instead). fit_noise: the
        first part's weak rows' whitener when the log states its targets' noise (weak_noise), for the t
        ratios of moves fitted on those rows (cv_polish.move_candidate). identify_on_all: a model's t ratios
        and VIFs (identification) are measured on all the parts' rows, under all_noise (the whitener of
        every part's weak rows in turn, weak_noise.stacked_whitener) when given, else on the fit rows under
        fit_noise."""
        if folds < 2:
            raise ValueError(f"cross-validation needs at least 2 folds, got {folds}")
        self.fit_noise = fit_noise
        self.all_noise = all_noise
        self.identify_on_all = identify_on_all
        self.parts = [p for p in parts if len(p[0])]
        ys = [np.asarray(y, float) if op is None else np.asarray(op @ y, float) for _, y, op, _ in self.parts]
        self.y = np.concatenate(ys) if ys else np.zeros(0)
        self._first = len(ys[0]) if ys else 0  # the first part's rows (the fit rows)
        n = len(self.y)
        self.folds = min(int(folds), max(n, 1))
        gap = max((g for *_, g in self.parts), default=0)
        # a block at least MIN_BLOCK_GAPS gaps long, so that a fold's fit keeps most rows beside its gaps
        most = n // max(MIN_BLOCK_GAPS * gap, 1)
        per_fold = max(1, min(int(blocks_per_fold), most // self.folds))
        self.usable = most >= self.folds  # else the gaps would leave the folds' fits (nearly) no rows
        count = min(self.folds * per_fold, max(n, 1))
        self.blocks = count
        bounds = np.linspace(0, n, count + 1).round().astype(int)
        # rows left out of fold k's fit: its blocks and `gap` rows either side of each
        self.held, self.dropped = [], []
        for k in range(self.folds):
            blocks = range(k, count, self.folds)
            self.held.append(np.concatenate([np.arange(bounds[b], bounds[b + 1]) for b in blocks]))
            drop = np.zeros(n, bool)
            for b in blocks:
                drop[max(bounds[b] - gap, 0):min(bounds[b + 1] + gap, n)] = True
            self.dropped.append(np.flatnonzero(drop))
        self._columns: dict[sympy.Expr, np.ndarray] = {}  # sympy expressions hash by structure
        self._index: dict[sympy.Expr, int] = {}  # prepare(): a term's column in the prepared Gram matrices
        self._offered: set[sympy.Expr] = set()  # every term prepare() was given (a non-finite one: no column)
        self._pool: _FoldEquations | None = None
        self._centred: CentredPool | None = None  # every term measured, on identification()'s rows
        self._centred_index: dict[sympy.Expr, int] = {}  # a term's column in _centred
        # identification() per term list: the engine's candidates are measured there, then re-aimed
        # (identify_on) and asked again by the pick
        self._identified: dict[tuple[sympy.Expr, ...], tuple[float, float]] = {}

    @property
    def scale(self) -> float:
        """The target's standard deviation over the rows (the pick's abs_tol scale)."""
        return float(np.std(self.y)) if len(self.y) else 1.0

    def column(self, shape: sympy.Expr) -> np.ndarray:
        """A term's values (M,) over the rows (weak rows integrated)."""
        if shape not in self._columns:
            values = []
            for X, _, op, _ in self.parts:
                col = expression_columns([shape], X)[:, 0]
                values.append(np.asarray(col if op is None else op @ col, float))
            self._columns[shape] = np.concatenate(values) if values else np.zeros(0)
        return self._columns[shape]

    def fit_part(self, shapes: Sequence[sympy.Expr]) -> tuple[np.ndarray, np.ndarray, int | None]:
        """The terms' columns (M,k) and the target (M,) on the first part's rows (the fit rows), and the
        lag of their rows' correlation for t ratios (the weak windows' overlap; None: point rows)."""
        a = np.column_stack([self.column(s)[:self._first] for s in shapes])
        op, gap = (self.parts[0][2], self.parts[0][3]) if self.parts else (None, 0)
        return a, self.y[:self._first], None if op is None else gap

    def identification(self, shapes: Sequence[sympy.Expr]) -> tuple[float, float]:
        """(weakest t ratio, largest VIF) of a linear model of these terms (collinearity.term_identification)
        on the rows its coefficients are measured on: all the parts' rows with identify_on_all (those the
        chosen structure is refit on, identification.refit), else the fit rows."""
        if not shapes:
            return float("inf"), 1.0  # no term to measure (as term_identification for no varying term)
        key = tuple(shapes)
        if key not in self._identified and (pooled := self._pooled_identification(shapes)) is not None:
            self._identified[key] = pooled
        if key not in self._identified:
            if self.identify_on_all:
                a, y = np.column_stack([self.column(s) for s in shapes]), self.y
                lag = None if not self.parts or self.parts[0][2] is None else self.parts[0][3]
                self._identified[key] = term_identification(a, y, lag, self.all_noise)
            else:
                a, y, lag = self.fit_part(shapes)
                self._identified[key] = term_identification(a, y, lag, self.fit_noise)
        return self._identified[key]

    def _pooled_identification(self, shapes: Sequence[sympy.Expr]) -> tuple[float, float] | None:
        """identification() on rows without stated noise from one QR factorisation of every term measured
        so far (collinearity.CentredPool), the terms not in it joined first; None where that does not
        answer (a term not finite there)."""
        if (self.all_noise if self.identify_on_all else self.fit_noise) is not None or not len(self.y):
            return None
        rows = slice(None) if self.identify_on_all else slice(0, self._first)
        if self._centred is None:
            lag = None if not self.parts or self.parts[0][2] is None else self.parts[0][3]
            self._centred = CentredPool(self.y[rows], lag)
        new = [s for s in dict.fromkeys(shapes) if s not in self._centred_index]
        cols = [self.column(s)[rows] for s in new]
        if not all(np.all(np.isfinite(c)) for c in cols):
            return None
        if new:
            at = self._centred.add(np.column_stack(cols))
            self._centred_index.update(zip(new, at, strict=True))
        return self._centred.identification([self._centred_index[s] for s in shapes])

    def prepare(self, shapes: Sequence[sympy.Expr]) -> None:
        """Precompute the Gram matrices of these terms (finite ones) over all rows and over each fold's
        dropped rows, so that a model of any of them is scored in O(k^3) per fold plus its held-out rows
        (cv_polish scores thousands of one-term moves over one pool of terms); those prepared before are
        dropped."""
        self._pool, self._index, self._offered = None, {}, set()
        self.extend(shapes)

    def extend(self, shapes: Sequence[sympy.Expr]) -> None:
        """Prepare these terms, keeping those prepared: the candidates' scoring and the polish share one
        pool, and a term joining it adds only its blocks of the Gram matrices (_FoldEquations.joined)."""
        new: dict[sympy.Expr, None] = {}
        cols = []
        for s in shapes:
            if s in self._offered:
                continue
            self._offered.add(s)
            col = self.column(s)
            if np.all(np.isfinite(col)):
                new[s] = None
                cols.append(col)
        if not cols or not len(self.y):
            return
        start = len(self._index)
        self._index.update({k: start + i for i, k in enumerate(new)})
        a = np.column_stack(cols)
        self._pool = (_FoldEquations(a, self.y, self.dropped, self.held, self._first) if self._pool is None
                      else self._pool.joined(a))

    def include(self, shapes: Sequence[sympy.Expr]) -> None:
        """Prepare these terms too, beside those prepared (nothing before a pool is): a polish move can bring
        in a term of no pool (a rotor pattern), and a model holding one would be scored move by move."""
        if self._pool is not None:
            self.extend(shapes)

    def fit_coefficients(self, shapes: Sequence[sympy.Expr]) -> np.ndarray | None:
        """The terms' least-squares coefficients on the fit rows (the target's unit per each term's), from
        the prepared normal equations; None when a term is not prepared or the equations are (nearly)
        singular (the caller solves by least squares)."""
        idx = [self._index.get(s) for s in shapes]
        if self._pool is None or not shapes or any(i is None for i in idx):
            return None
        return self._pool.fit_coefficients(idx)

    def predictions(self, shapes: Sequence[sympy.Expr]) -> np.ndarray:
        """Each row's prediction by the terms refit (least squares) without the row's fold; NaN when a
        term is not finite."""
        if not len(self.y):
            return np.zeros(0)
        idx = [self._index.get(s) for s in shapes]
        if self._pool is not None and all(i is not None for i in idx):  # prepared: submatrices
            return self._pool.predictions(idx)
        a = np.column_stack([self.column(s) for s in shapes])
        if not np.all(np.isfinite(a)):
            return np.full(len(self.y), np.nan)
        return _FoldEquations(a, self.y, self.dropped, self.held).predictions(list(range(len(shapes))))

    def move_losses(self, current: Sequence[sympy.Expr], others: Sequence[sympy.Expr],
                    kind: str) -> tuple[np.ndarray, np.ndarray] | None:
        """The cross-validated losses of every one-term move of the model `current` onto `others` at once:
        (swaps (k, P): term i replaced by others[p]; additions (P,): others[p] added), each what
        terms_loss gives that model up to rounding; inf where the move's new term is (nearly) a combination
        of the terms it joins on a fold's rows (no loss: the rows cannot tell its coefficient from theirs);
        NaN where the batch cannot answer (a term not prepared, current's own columns (nearly) dependent:
        terms_loss answers those). None before prepare()."""
        if self._pool is None or not len(self.y):
            return None
        base, ok, idx = self._pool_indices(current, others)
        if base is None:
            return None
        swaps = np.full((len(base), len(others)), np.nan)
        adds = np.full(len(others), np.nan)
        if not ok.any():
            return swaps, adds
        cols = idx[ok]
        batch = self._pool.move_losses(base, cols, kind)
        if batch is not None:
            swaps[:, ok], adds[ok] = batch
            return swaps, adds
        for row, kept in [(i, base[:i] + base[i + 1:]) for i in range(len(base))] + [(None, base)]:
            values = self._pool.added_losses(kept, cols, kind)
            if row is None:
                adds[ok] = values
            else:
                swaps[row, ok] = values
        return swaps, adds

    def addition_losses(self, current: Sequence[sympy.Expr], others: Sequence[sympy.Expr],
                        kind: str) -> np.ndarray:
        """The cross-validated loss of current + [o] for each o of others (P,) at once, as terms_loss gives
        it up to rounding; NaN where the batch cannot answer (a term not prepared, current's equations
        singular on a fold's rows, o (nearly) a combination of current's terms there)."""
        out = np.full(len(others), np.nan)
        if self._pool is None or not len(self.y):
            return out
        base, ok, idx = self._pool_indices(current, others)
        if base is None or not ok.any():
            return out
        out[ok] = self._pool.added_losses(base, idx[ok], kind)
        return out

    def _pool_indices(self, current: Sequence[sympy.Expr], others: Sequence[sympy.Expr]
                      ) -> tuple[list[int] | None, np.ndarray, np.ndarray]:
        """current's columns in the pool (None when one is not prepared), which of others are prepared
        (bool (P,)) and their columns (P,; -1 where not)."""
        base = [self._index.get(s) for s in current]
        extra = [self._index.get(s) for s in others]
        ok = np.asarray([i is not None for i in extra], bool)
        idx = np.asarray([-1 if i is None else i for i in extra], int)
        return (None if any(i is None for i in base) else base), ok, idx

    def terms_loss(self, shapes: Sequence[sympy.Expr], kind: str) -> float:
        """The cross-validated loss of a model of these terms; inf when a term is not finite."""
        return loss_fn(self.y, self.predictions(shapes), kind) if len(self.y) else float("inf")

    def loss(self, expression: sympy.Expr, kind: str) -> float:
        """The cross-validated loss of an expression's terms (module docstring); inf when not finite."""
        shapes = term_shapes(expression)
        return self.terms_loss(shapes, kind) if shapes else loss_fn(self.y, np.zeros_like(self.y), kind)


# move_losses sums each set's errors over row blocks of about this many values (512 kB: the block and its
# errors stay in a core's cache across the sets)
_BLOCK_VALUES = 65536

# move_losses' rank-one updates answer while base's largest VIF (on a fold's uncentred unit-RMS columns) is
# below this; above it, added_losses solves each set's own equations
_DOWNDATE_MAX_VIF = 1e8


class _FoldEquations:
    """The normal equations of columns a (M,m), scaled to unit RMS, over all rows, over each fold's
    dropped rows and over the first `first` rows (the fit rows): a model of any subset of the columns is
    refit per fold, or on the fit rows, from their submatrices."""

    def __init__(self, a: np.ndarray, y: np.ndarray, dropped: Sequence[np.ndarray],
                 held: Sequence[np.ndarray], first: int = 0):
        size = np.sqrt(np.mean(a * a, axis=0))
        size[size == 0] = 1.0
        self.size = size
        self.a = a / size
        self.y = y
        self.gram, self.rhs = self.a.T @ self.a, self.a.T @ y
        self._first = first
        self.dropped = list(dropped)
        self.dropped_gram = [self.a[d].T @ self.a[d] for d in dropped]
        self.dropped_rhs = [self.a[d].T @ y[d] for d in dropped]
        self.held = list(held)

    def joined(self, b: np.ndarray) -> _FoldEquations:
        """These equations with columns b (M,n) after the kept ones: only the blocks of b's products are
        computed (a polish pool of 360 terms and 15,000 rows took 1.4 s to rebuild for each new term)."""
        size = np.sqrt(np.mean(b * b, axis=0))
        size[size == 0] = 1.0
        b = b / size
        new = object.__new__(_FoldEquations)
        new.size = np.concatenate([self.size, size])
        new.a = np.hstack([self.a, b])
        new.y, new._first, new.dropped, new.held = self.y, self._first, self.dropped, self.held

        def grown(gram: np.ndarray, rhs: np.ndarray, a: np.ndarray, b: np.ndarray, y: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
            cross = a.T @ b
            return np.block([[gram, cross], [cross.T, b.T @ b]]), np.concatenate([rhs, b.T @ y])

        new.gram, new.rhs = grown(self.gram, self.rhs, self.a, b, self.y)
        parts = [grown(g, r, self.a[d], b[d], self.y[d])
                 for g, r, d in zip(self.dropped_gram, self.dropped_rhs, self.dropped, strict=True)]
        new.dropped_gram = [g for g, _ in parts]
        new.dropped_rhs = [r for _, r in parts]
        return new

    @functools.cached_property
    def fit_gram(self) -> np.ndarray:
        """The normal matrix over the fit rows (made when first asked for: a candidate scored on its own
        columns never asks)."""
        fit = self.a[:self._first]
        return fit.T @ fit

    @functools.cached_property
    def fit_rhs(self) -> np.ndarray:
        """The right-hand side over the fit rows."""
        return self.a[:self._first].T @ self.y[:self._first]

    @functools.cached_property
    def held_a(self) -> list[np.ndarray]:
        """Each fold's held-out rows column-major: a model's columns are then contiguous copies (a gather
        by rows and columns at once was most of cv_polish's time); made when a subset is first scored."""
        return [np.asfortranarray(self.a[rows]) for rows in self.held]

    def predictions(self, idx: Sequence[int]) -> np.ndarray:
        """Each held-out row's prediction by columns idx refit without its fold's dropped rows."""
        idx = list(idx)
        # every column in order (a candidate scored on its own columns): the whole matrices, and the held
        # rows as they are, row-major as the subsets' copies below: the same sums without the copies (a
        # heavy closed loop's 867 candidates scored in 4.0-4.5 s against 8.0, every loss the same to the bit)
        whole = idx == list(range(self.a.shape[1]))
        sub = (slice(None), slice(None)) if whole else np.ix_(idx, idx)
        grams = np.stack([self.gram[sub] - d[sub] for d in self.dropped_gram])
        rhs = np.stack([self.rhs[idx] - d[idx] for d in self.dropped_rhs])
        out = np.empty(len(self.a))
        for k, (rows, coef) in enumerate(zip(self.held, _solve(grams, rhs), strict=True)):
            a = self.a[rows] if whole else np.ascontiguousarray(self.held_a[k][:, idx])
            out[rows] = a @ coef
        return out

    def fit_coefficients(self, idx: Sequence[int]) -> np.ndarray | None:
        """Columns idx's least-squares coefficients on the fit rows (per unscaled column); None when their
        equations there are singular or their largest VIF is above _DOWNDATE_MAX_VIF."""
        idx = list(idx)
        g = self.fit_gram[np.ix_(idx, idx)]
        try:
            w = np.linalg.solve(g, np.column_stack([self.fit_rhs[idx], np.eye(len(idx))]))
        except np.linalg.LinAlgError:
            return None
        vif = np.diag(w[:, 1:]) * np.diag(g)
        if not np.all(vif > 0) or float(np.max(vif)) > _DOWNDATE_MAX_VIF:
            return None
        return w[:, 0] / self.size[idx]

    def move_losses(self, base: Sequence[int], extra: np.ndarray, kind: str
                    ) -> tuple[np.ndarray, np.ndarray] | None:
        """added_losses for base less each of its columns in turn (swaps (k, P)) and for base itself (adds
        (P,)), from one solve of base's normal equations per fold: dropping column i changes base's fits by
        a rank-one term (coefficients b - h_i b_i / H_ii, H the inverse normal matrix, h_i its column i),
        so each swap's prediction is base's plus that term, where added_losses solves anew and multiplies
        the held rows by a (k, P) matrix for each of the k + 1 sets. The same least squares up to rounding;
        None (added_losses set by set) when base's equations on a fold are singular or nearly so
        (_DOWNDATE_MAX_VIF)."""
        base = list(base)
        k, count = len(base), len(extra)
        if k == 0:
            return None
        both, sub = np.ix_(base, base), np.ix_(base, extra)
        # the whole rows' parts, the same for every fold (each fold's dropped rows are taken from them)
        gram_bb, gram_bx, diag_x = self.gram[both], self.gram[sub], np.diag(self.gram)[extra]
        rhs_b, rhs_x = self.rhs[base], self.rhs[extra]
        total = np.zeros((k + 1, count))  # row k: base itself (the additions)
        usable = np.ones((k + 1, count), bool)
        for d_gram, d_rhs, rows, a in zip(self.dropped_gram, self.dropped_rhs, self.held, self.held_a,
                                          strict=True):
            g = gram_bb - d_gram[both]
            g_bx = gram_bx - d_gram[sub]
            try:
                w = np.linalg.solve(g, np.column_stack([rhs_b - d_rhs[base], g_bx, np.eye(k)]))
            except np.linalg.LinAlgError:
                return None
            b0, v, h = w[:, 0], w[:, 1:1 + count], np.diag(w[:, 1 + count:])
            if not np.all(h > 0) or float(np.max(h * np.diag(g))) > _DOWNDATE_MAX_VIF:
                return None
            g_xx = diag_x - np.diag(d_gram)[extra]
            schur = g_xx - np.sum(g_bx * v, axis=0)
            num = (rhs_x - d_rhs[extra]) - g_bx.T @ b0
            a_b = a[:, base]
            e = self.y[rows] - a_b @ b0  # base's errors on the held rows
            q = a_b @ w[:, 1 + count:]
            r = a[:, extra] - a_b @ v  # each extra column less its fit by base's columns
            floor = 1e-9 * np.maximum(g_xx, 1e-300)
            # each set's coefficients of the new column (beta), of the rank-one part (c beta) and of its
            # shift of base's errors: set i drops base's column i, set k is base itself (the additions)
            betas, ranks, shifts = np.empty((k + 1, count)), np.zeros((k + 1, count)), np.zeros(k + 1)
            for i in range(k + 1):
                s, top = schur, num
                if i < k:
                    c = v[i] / h[i]
                    s, top, shifts[i] = schur + v[i] * c, num + b0[i] * c, b0[i] / h[i]
                usable[i] &= s > floor
                betas[i] = top / np.where(s > 0, s, 1.0)
                if i < k:
                    ranks[i] = c * betas[i]
            # row blocks a few hundred kB wide, each set's errors summed over one block at a time: the
            # block stays in the core's cache across the sets (one pass over all the held rows per set
            # was memory-bound: 1.5x slower on 3,000 rows and 360 columns)
            step = max(32, _BLOCK_VALUES // max(count, 1))
            fit = np.empty((min(step, len(rows)), count))
            for start in range(0, len(rows), step):
                part = slice(start, start + step)
                r_p, q_p, e_p = r[part], q[part], e[part]
                f = fit[:len(e_p)]
                for i in range(k + 1):
                    np.multiply(r_p, betas[i], out=f)
                    if i < k:  # the rank-one part: fit += q_i (c beta)^T, on errors shifted by q_i
                        f += q_p[:, i, None] * ranks[i]
                        np.subtract((e_p + q_p[:, i] * shifts[i])[:, None], f, out=f)
                    else:
                        np.subtract(e_p[:, None], f, out=f)
                    if kind == "absolute":
                        np.abs(f, out=f)
                    else:
                        np.multiply(f, f, out=f)
                    total[i] += f.sum(axis=0)
        with np.errstate(all="ignore"):
            value = total / len(self.a) if kind == "absolute" else np.sqrt(total / len(self.a))
        value = np.where(np.isfinite(value), value, np.inf)
        value[~usable] = np.inf  # a combination of the kept terms: a model the rows do not identify
        return value[:k], value[k]

    def added_losses(self, kept: Sequence[int], extra: np.ndarray, kind: str,
                     chunk: int = 64) -> np.ndarray:
        """The cross-validated loss of columns kept + [j] for each j of extra (P,), all at once: per fold,
        kept's normal equations solved once and each extra column joined by its Schur complement (the
        same least squares as predictions(kept + [j])). NaN where kept's equations are singular or column j
        is (nearly) a combination of kept's on a fold's rows."""
        kept = list(kept)
        out = np.full(len(extra), np.nan)
        preds = np.empty((len(self.a), len(extra)))
        # the whole rows' parts, the same for every fold (each fold's dropped rows are taken from them)
        diag, rhs_x, rhs_k = np.diag(self.gram)[extra], self.rhs[extra], self.rhs[kept]
        gram_kx, gram_kk = self.gram[np.ix_(kept, extra)], self.gram[np.ix_(kept, kept)]
        usable = np.ones(len(extra), bool)
        for d_gram, d_rhs, rows, a in zip(self.dropped_gram, self.dropped_rhs, self.held, self.held_a,
                                          strict=True):
            g_kx = gram_kx - d_gram[np.ix_(kept, extra)]
            g_xx = diag - np.diag(d_gram)[extra]
            r_x = rhs_x - d_rhs[extra]
            if kept:
                g_kk = gram_kk - d_gram[np.ix_(kept, kept)]
                try:
                    w = np.linalg.solve(g_kk, np.column_stack([rhs_k - d_rhs[kept], g_kx]))
                except np.linalg.LinAlgError:
                    return out
                b0, v = w[:, 0], w[:, 1:]
                schur = g_xx - np.sum(g_kx * v, axis=0)
                num = r_x - g_kx.T @ b0
                a_k = a[:, kept]
                base = a_k @ b0
            else:
                b0 = v = None
                schur, num, base = g_xx, r_x, np.zeros(len(rows))
            usable &= schur > 1e-9 * np.maximum(g_xx, 1e-300)
            beta = num / np.where(schur > 0, schur, 1.0)
            for start in range(0, len(extra), chunk):
                part = slice(start, start + chunk)
                resid = a[:, extra[part]]
                if v is not None:
                    resid = resid - a_k @ v[:, part]
                preds[rows, part] = base[:, None] + resid * beta[part]
        for start in range(0, len(extra), chunk):
            part = slice(start, start + chunk)
            err = self.y[:, None] - preds[:, part]
            with np.errstate(all="ignore"):
                value = (np.mean(np.abs(err), axis=0) if kind == "absolute"
                         else np.sqrt(np.mean(err * err, axis=0)))
            out[part] = np.where(np.all(np.isfinite(preds[:, part]), axis=0), value, np.inf)
        out[~usable] = np.nan
        return out


def _solve(grams: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Each fold's normal equations (K,k,k) x = (K,k) solved at once; a singular one (duplicate terms)
    by least squares, the minimum-norm solution."""
    try:
        return np.linalg.solve(grams, rhs[..., None])[..., 0]
    except np.linalg.LinAlgError:
        return np.stack([np.linalg.lstsq(g, r, rcond=1e-13)[0] for g, r in zip(grams, rhs, strict=True)])


def attach_cross_validated(candidates: Sequence[Candidate], rows: FoldedRows, kind: str) -> None:
    """Set each candidate's held-out loss to its cross-validated loss over `rows`, each model refit from the
    submatrices of one pool of every candidate's terms (FoldedRows.extend): a thousand candidates of a
    closed-loop target share a few hundred terms, and each one's own normal equations were most of the
    time (racer closed loop, seed 89, dwx: 7.9 s against 1.1)."""
    with single_threaded_blas():
        shapes: dict[sympy.Expr, None] = {}
        for c in candidates:
            try:
                shapes.update(dict.fromkeys(term_shapes(c.expression)))
            except (ValueError, TypeError):
                continue  # scored (inf) below
        rows.extend(list(shapes))
        for c in candidates:
            try:
                c.holdout_loss = rows.loss(c.expression, kind)
            except (ValueError, TypeError, ZeroDivisionError, OverflowError, np.linalg.LinAlgError):
                c.holdout_loss = float("inf")


def identify_on(candidates: Sequence[Candidate], rows: FoldedRows) -> None:
    """Re-aim each measured candidate's t ratio and VIF (Candidate.measure) at the rows
    FoldedRows.identification measures on; a candidate its engine does not measure (not linear in its
    terms) stays unmeasured."""
    for c in candidates:
        if c.measure is None and c.weakest_t is None and c.largest_vif is None:
            continue
        shapes = term_shapes(c.expression)
        if not shapes:
            continue
        c.weakest_t = c.largest_vif = None
        c.measure = functools.partial(rows.identification, shapes)
