"""Sparse regression over the physics-informed library: sequentially thresholded least squares (STLSQ).

Features are scaled to unit spread; a term's contribution is |coefficient| x feature std (RMS for the
constant) relative to the target's std. STLSQ removes the terms whose contribution is below a threshold and
refits by least squares until the set is stable. A log-spaced sweep of the threshold, plus the
backward-elimination path (drop the smallest contribution, refit, down to one term), gives candidates of every
size. With loss 'absolute' each candidate's coefficients are refit for the absolute error (IRLS).
"""

from __future__ import annotations

import contextlib
import functools
import time
from collections.abc import Callable, Iterator, Sequence

import numpy as np
import scipy.linalg
import sympy

from identification.candidate import Candidate, Progress
from identification.engine_settings import SparseSettings
from identification.library import Feature, build_library, compile_features
from identification.metrics import LOSSES
from identification.metrics import loss as loss_fn
from identification.model_file import complexity


class LeastSquaresProblem:
    """The scaled least-squares problem of one target, reduced once by QR.

    With [S | y] = QR (N x (p+1)), min ||S_A x - y|| over a column subset A equals min ||R_A x - z|| for z
    R's last column: every subset solve afterwards is a (p+1) x |A| problem, independent of the number of
    samples.
    """

    def __init__(self, theta: np.ndarray, y: np.ndarray, weights: np.ndarray | None = None):
        """weights (N,) >= 0: row weights of every least-squares solve and path (identification.
        robust_weights); the absolute-error refit (l1_refit) and the scales stay those of the plain rows."""
        self.theta = theta
        self.y = y
        self.y_std = float(np.std(y)) or float(np.sqrt(np.mean(y * y))) or 1.0
        std = theta.std(axis=0)
        rms = np.sqrt(np.mean(theta * theta, axis=0))
        self.is_const = std <= 1e-12 * np.maximum(rms, 1e-300)
        size = np.where(self.is_const, rms, std)
        self.usable = size > 0
        self.size = np.where(self.usable, size, 1.0)
        w = None if weights is None else np.asarray(weights, dtype=float)
        self.y_mean = float(np.average(y, weights=w))
        self.mean = np.average(theta, axis=0, weights=w)
        scaled = theta / self.size
        self.scaled = scaled
        sw = np.ones(len(y)) if w is None else np.sqrt(w)
        consts = np.flatnonzero(self.is_const & self.usable)
        self.const_col = int(consts[0]) if consts.size == 1 else None
        p = theta.shape[1]
        c0 = self.const_col
        # one R-only factorisation of [S | y] with the constant column first: the rows after the first are
        # the factor of the weighted-centred problem (the first reflection removes the weighted mean), far
        # better conditioned when features have large means (f1 ~ 1e6)
        order = np.arange(p) if c0 is None else np.r_[c0, np.delete(np.arange(p), c0)]
        r = self._reduce(np.column_stack([scaled[:, order] * sw[:, None], y * sw]))
        m = min(r.shape[0], p + 1)
        self._r_u = np.zeros((m, p))
        self._r_u[:, order] = r[:m, :p]
        self._z_u = r[:m, p].copy()
        self._y2 = float((y * sw) @ (y * sw))
        self._y_c2 = float((((y - self.y_mean) * sw) ** 2).sum())
        self._solved: dict[tuple, np.ndarray] = {}  # solve()'s answers by active set
        if c0 is not None:
            self._r_c = np.zeros((max(m - 1, 0), p))
            self._r_c[:, order[1:]] = r[1:m, 1:p]
            self._z_c = r[1:m, p].copy()

    @staticmethod
    def _reduce(a: np.ndarray) -> np.ndarray:
        """The upper-triangular factor R of a = QR (Q not formed)."""
        return np.linalg.qr(np.asfortranarray(a), mode="r")

    def solve(self, active: np.ndarray) -> np.ndarray:
        """Least-squares coefficients (original units) on the active columns; zeros elsewhere."""
        # kept: every threshold of the sweep starts from the same full set, and the sets it and the paths
        # reach are solved again when they become candidates
        key = (active.dtype.str, active.shape, active.tobytes())
        if key not in self._solved:
            self._solved[key] = self._solve(active)
        return self._solved[key].copy()

    def _solve(self, active: np.ndarray) -> np.ndarray:
        coef = np.zeros(self.theta.shape[1])
        idx = np.flatnonzero(active)
        if idx.size == 0:
            return coef
        c0 = self.const_col
        if c0 is not None and active[c0]:
            others = idx[idx != c0]
            if others.size:
                sol = lstsq_by_qr(self._r_c[:, others], self._z_c)[0]
                coef[others] = sol / self.size[others]
            coef[c0] = (self.y_mean - float(self.mean[others] @ coef[others])) / self.mean[c0]
            return coef
        sol = lstsq_by_qr(self._r_u[:, idx], self._z_u)[0]
        coef[idx] = sol / self.size[idx]
        return coef

    def rss_reduced(self, active: np.ndarray) -> float:
        """Residual sum of squares of the least-squares fit on the active columns, up to a constant.

        The constant differs between fits with and without the constant column, so compare like with like.
        """
        idx = np.flatnonzero(active)
        c0 = self.const_col
        if c0 is not None and active[c0]:
            others = idx[idx != c0]
            r, z = self._r_c[:, others], self._z_c
            offset = float(self._y_c2 - z @ z)
        else:
            r, z = self._r_u[:, idx], self._z_u
            offset = float(self._y2 - z @ z)
        if r.shape[1] == 0:
            return float(z @ z) + offset
        x = lstsq_by_qr(r, z)[0]
        d = z - r @ x
        return float(d @ d) + offset

    def rss(self, idx: np.ndarray) -> float:
        """Residual sum of squares of the least-squares fit on columns idx (uncentred problem)."""
        z = self._z_u
        if idx.size == 0:
            return self._y2
        q = range_basis(self._r_u[:, idx])
        resid = z - q @ (q.T @ z)
        return float(resid @ resid) + self._y2 - float(z @ z)

    def removal_costs(self, idx: np.ndarray, factor: np.ndarray | None = None) -> np.ndarray:
        """For each column of idx, how much the RSS rises without it: x_j^2 / [(M^T M)^-1]_jj, vectorised.

        factor: the triangular factor of [M | z] for M = the reduced columns idx (subset_factor), when
        the caller keeps it up to date (backward_path); computed here otherwise."""
        k = idx.size
        t = self.subset_factor(idx) if factor is None else factor
        r = t[:k, :k]
        diag = np.abs(np.diag(r))
        if diag.size and independent_pivots(diag):  # else dependent columns
            rinv, info = scipy.linalg.lapack.dtrtri(r, lower=0)
            if info == 0:
                x = rinv @ t[:k, k]
                return x * x / np.sum(rinv * rinv, axis=1)
        return dependent_removal_costs(r, t[:k, k])

    def subset_factor(self, idx: np.ndarray) -> np.ndarray:
        """The triangular factor (at most k+1 rows) of [M | z] for M the reduced columns idx (k of them) and
        z the reduced target: its first k columns are M's R, its last column's first k entries R's Q^T z."""
        t = np.linalg.qr(np.asfortranarray(np.column_stack([self._r_u[:, idx], self._z_u])), mode="r")
        return t[: idx.size + 1]

    def addition_gains(self, idx: np.ndarray, candidates: np.ndarray) -> np.ndarray:
        """For each candidate column, how much the RSS falls when it joins idx, vectorised."""
        z = self._z_u
        cols = self._r_u[:, candidates]
        if idx.size:
            q = range_basis(self._r_u[:, idx])
            resid = z - q @ (q.T @ z)
            cols = cols - q @ (q.T @ cols)
        else:
            resid = z
        den = np.sum(cols * cols, axis=0)
        num = (resid @ cols) ** 2
        scale = np.sum(self._r_u[:, candidates] ** 2, axis=0)
        return np.where(den > 1e-12 * np.maximum(scale, 1e-300), num / np.where(den > 0, den, 1.0), 0.0)

    def contribution(self, coef: np.ndarray) -> np.ndarray:
        """Each term's size relative to the target's spread."""
        return np.abs(coef) * self.size / self.y_std

    def l1_refit(self, active: np.ndarray, coef: np.ndarray, iterations: int) -> np.ndarray:
        """Refit the active coefficients for the least absolute error (IRLS); keeps LS if not better."""
        idx = np.flatnonzero(active)
        if idx.size == 0 or iterations <= 0:
            return coef
        a = self.scaled[:, idx]
        x = coef[idx] * self.size[idx]
        r = self.y - a @ x
        best_x, best_mae = x, float(np.mean(np.abs(r)))
        if best_mae <= 1e-9 * self.y_std:
            return coef  # exact already: nothing for IRLS to gain
        eps = max(1e-3 * float(np.median(np.abs(r))), 1e-12 * self.y_std)
        for _ in range(iterations):
            w = 1.0 / np.maximum(np.abs(r), eps)
            x_new = _weighted_solve(a, self.y, w)
            r = self.y - a @ x_new
            mae = float(np.mean(np.abs(r)))
            if mae < best_mae:
                best_x, best_mae, improvement = x_new, mae, best_mae - mae
                if improvement < 1e-3 * best_mae:
                    break
            else:
                break
        out = np.zeros_like(coef)
        out[idx] = best_x / self.size[idx]
        return out


# a term set's factor with a pivot (independent_pivots) or singular value (numerical_rank) at or below this
# fraction of the largest: dependent columns
RANK_TOLERANCE = 1e-10


def independent_pivots(diag: np.ndarray) -> bool:
    """Whether a triangular factor's pivots (|diag|, not empty) say its columns are independent."""
    return bool(diag.min() > RANK_TOLERANCE * diag.max())


def numerical_rank(sv: np.ndarray) -> int:
    """How many singular values (descending) are above RANK_TOLERANCE of the largest."""
    return int(np.sum(sv > RANK_TOLERANCE * sv[0])) if sv.size and sv[0] > 0 else 0


def removal_choice(costs: np.ndarray, idx: np.ndarray) -> int:
    """The position of the term a path drops: of dependent terms (cost 0) the one latest in the pool's
    order (the pool lists the simpler features first), else the cheapest."""
    zero = np.flatnonzero(costs == 0.0)
    return int(zero[np.argmax(idx[zero])]) if zero.size else int(np.argmin(costs))


def range_basis(m: np.ndarray) -> np.ndarray:
    """An orthonormal basis (n, rank) of m's column space: QR's Q when m's columns are independent, SVD's
    leading left vectors otherwise (a QR of dependent columns is still k orthonormal columns, the extra ones
    along rounding directions m does not span, and projections onto it fit the target along them too)."""
    q, r = np.linalg.qr(m, mode="reduced")
    diag = np.abs(np.diag(r))
    if diag.size == 0 or independent_pivots(diag):
        return q
    u, sv, _ = np.linalg.svd(m, full_matrices=False)
    return u[:, : numerical_rank(sv)]


def dependent_removal_costs(r: np.ndarray, w: np.ndarray) -> np.ndarray:
    """removal_costs where the columns are (nearly) dependent, from their triangular factor r (k, k) and
    w = Q^T z (k,): 0 for a column in a dependency (the others span it: without it the fit is the same),
    else x_j^2 / [G^+]_jj with x the minimum-norm solution and G^+ the pseudo-inverse of the columns' Gram
    matrix (what the full-rank formula is on the columns' independent part). One SVD of r (k x k), where
    one QR refit per column had taken 85 s of a 4 s flight's identify, and a QR of dependent columns spans
    directions they do not: those refits fitted z along them (costs off by more than the residual), and
    which dependent column went first was the arithmetic's last bits."""
    k = r.shape[1]
    if k == 0:
        return np.zeros(0)
    u, sv, vt = np.linalg.svd(r)
    rank = numerical_rank(sv)
    v = vt[:rank].T / sv[:rank]  # V_r S_r^-1 (k, rank): r^+ = V_r S_r^-1 U_r^T
    x = v @ (u[:, :rank].T @ w)
    diag = np.sum(v * v, axis=1)  # diag of G^+ = r^+ r^+^T
    null = vt[rank:].T  # (k, k - rank): the columns' dependencies
    # a column with a share in some dependency: its null-space entries are O(1) (a null vector is unit),
    # rounding's 1e-12 elsewhere
    in_dependency = np.linalg.norm(null, axis=1) > 1e-6
    with np.errstate(divide="ignore", invalid="ignore"):
        costs = np.where(diag > 0.0, x * x / np.where(diag > 0.0, diag, 1.0), 0.0)
    return np.where(in_dependency, 0.0, costs)


def lstsq_by_qr(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares x of a x = b (a (n, k); b (n,) or (n, m)) and the norm of what is left (per column of
    b): by the triangular factor of [a | b] when a's columns are independent, by SVD (np.linalg.lstsq)
    otherwise (near-dependent columns: its minimum-norm answer)."""
    n, k = a.shape
    if 0 < k <= n:
        r = np.linalg.qr(np.column_stack([a, b]), mode="r")
        d = np.abs(np.diag(r[:k, :k]))
        if independent_pivots(d):
            rhs = r[:k, k] if b.ndim == 1 else r[:k, k:]
            rest = r[k:, k] if b.ndim == 1 else r[k:, k:]
            return scipy.linalg.solve_triangular(r[:k, :k], rhs), np.linalg.norm(rest, axis=0)
    x = np.linalg.lstsq(a, b, rcond=None)[0]
    return x, np.linalg.norm(b - a @ x, axis=0)


def _weighted_solve(a: np.ndarray, y: np.ndarray, w: np.ndarray) -> np.ndarray:
    """argmin sum w (y - a x)^2: normal equations (k x k, fast) when well conditioned, else least squares."""
    aw = a * w[:, None]
    gram = aw.T @ a
    d = np.sqrt(np.clip(np.diag(gram), 1e-300, None))
    g = gram / np.outer(d, d)  # unit diagonal: the condition number is the columns', not their scales'
    if np.linalg.cond(g) < 1e8:
        return np.linalg.solve(g, (aw.T @ y) / d) / d
    sw = np.sqrt(w)
    return np.linalg.lstsq(a * sw[:, None], y * sw, rcond=None)[0]


def stlsq(
    problem: LeastSquaresProblem, threshold: float, active: np.ndarray, max_iterations: int
) -> np.ndarray:
    """STLSQ from `active` at one contribution threshold -> the final active set."""
    active = active.copy()
    for _ in range(max_iterations):
        coef = problem.solve(active)
        keep = active & (problem.contribution(coef) >= threshold)
        if np.array_equal(keep, active) or not keep.any():
            return keep if keep.any() else active
        active = keep
    return active


def backward_path(problem: LeastSquaresProblem, active: np.ndarray) -> list[np.ndarray]:
    """Active sets from `active` down to one term, each time dropping the term whose removal raises the
    residual sum of squares least (of two near-collinear terms one goes early, not both kept large)."""
    out = []
    idx = np.flatnonzero(active)
    factor = problem.subset_factor(idx) if idx.size else None
    while idx.size:
        current = np.zeros_like(active)
        current[idx] = True
        out.append(current)
        if idx.size == 1:
            break
        j = removal_choice(problem.removal_costs(idx, factor), idx)
        idx = np.delete(idx, j)
        # the factor without column j, by Givens rotations (O(k^2)) rather than a new QR (O(p k^2))
        rows = factor.shape[0]
        factor = scipy.linalg.qr_delete(np.eye(rows), factor, j, which="col", check_finite=False)[1]
        factor = factor[: idx.size + 1]
    return out


def forward_path(
    problem: LeastSquaresProblem, usable: np.ndarray, max_terms: int, prune: float = 1e-3,
    initial: np.ndarray | None = None,
) -> list[np.ndarray]:
    """Forward selection with pruning: add the term that lowers the residual most, then drop every earlier
    term whose removal raises the residual sum of squares by less than `prune` of it (a term made redundant
    by a better one, e.g. v|v| once the body-drag terms are in); one active set per step, until max_terms
    terms. initial: column indices to start from (a model found before) instead of none."""
    out = []
    idx = np.zeros(0, dtype=int) if initial is None else np.asarray(initial, dtype=int)
    idx = idx[usable[idx]]
    for _ in range(min(max_terms - idx.size, int(usable.sum()) - idx.size)):
        pool = np.flatnonzero(usable & ~np.isin(np.arange(usable.size), idx))
        if pool.size == 0:
            break
        gains = problem.addition_gains(idx, pool)
        if not np.any(gains > 0):
            break
        new = int(pool[int(np.argmax(gains))])
        idx = np.append(idx, new)
        while idx.size > 1:
            costs = problem.removal_costs(idx)
            costs[idx == new] = np.inf
            k = removal_choice(costs, idx)
            if costs[k] > prune * max(problem.rss(idx), 1e-300):
                break
            idx = np.delete(idx, k)
        current = np.zeros_like(usable)
        current[idx] = True
        out.append(current)
    return out


def simpler_swaps(
    active: np.ndarray, usable: np.ndarray, groups: Sequence[str], nodes: Sequence[int]
) -> list[np.ndarray]:
    """Each set with one term replaced by a simpler term of the same group (wz for wz*wz, say).

    Where the data cannot tell two terms apart by the training residual (a yaw rate that never changes
    sign makes wz and wz*wz alike), the simpler one gets a chance on the held-out data.
    """
    out = []
    for i in np.flatnonzero(active):
        for j in np.flatnonzero(usable & ~active):
            if groups[j] == groups[i] and nodes[j] < nodes[i]:
                swapped = active.copy()
                swapped[i] = False
                swapped[j] = True
                out.append(swapped)
    return out


def sparse_active_sets(
    problem: LeastSquaresProblem,
    settings: SparseSettings,
    progress: Progress | None = None,
    groups: Sequence[str] | None = None,
    nodes: Sequence[int] | None = None,
    initial: np.ndarray | None = None,
    addable: np.ndarray | None = None,
) -> list:
    """Unique active sets from the threshold sweep, the backward and the forward paths (and simpler swaps);
    initial: column indices of a model found before, from which a second forward path goes on, adding only
    the columns `addable` (bool per column; None: any)."""
    start = problem.usable.copy()
    sets: dict[bytes, np.ndarray] = {}
    thresholds = np.geomspace(settings.threshold_min, settings.threshold_max, max(settings.thresholds, 1))
    for i, thr in enumerate(thresholds):
        a = stlsq(problem, float(thr), start, settings.max_iterations)
        sets.setdefault(a.tobytes(), a)
        if progress:
            progress(0.5 * (i + 1) / len(thresholds), f"threshold {thr:.1e}")
    if settings.backward:
        for a in backward_path(problem, start):
            sets.setdefault(a.tobytes(), a)
    if settings.forward_terms:
        for a in forward_path(problem, start, settings.forward_terms):
            sets.setdefault(a.tobytes(), a)
            if groups is not None and nodes is not None and np.count_nonzero(a) <= settings.swap_max_terms:
                for b in simpler_swaps(a, start, groups, nodes):
                    sets.setdefault(b.tobytes(), b)
        if initial is not None and len(initial):
            grow = start.copy() if addable is None else start & addable
            grow[initial] = start[initial]
            for a in forward_path(problem, grow, settings.forward_terms, initial=initial):
                sets.setdefault(a.tobytes(), a)
    return list(sets.values())


ADD_ORDER = functools.cmp_to_key(sympy.Basic.compare)  # sympy's order of a sum's terms (its number first)


def _term(coef: float, feature: sympy.Expr) -> sympy.Expr:
    c = sympy.Float(float(coef))
    if feature == 1:
        return c
    args = feature.args if isinstance(feature, sympy.Mul) else (feature,)
    return sympy.Mul(c, *args, evaluate=False)  # unevaluated: keeps c*(u1**2 + ...) as written


def sparse_expression(features: Sequence[Feature], coef: np.ndarray, ordered: bool = False) -> sympy.Expr:
    """sum of coefficient x feature over the nonzero coefficients, as written (unevaluated); ordered: its
    terms in the order sympy's sum gives them (the number first), so that reading its terms back
    (collinearity.term_shapes) need not rebuild the sum."""
    terms = [_term(c, features[j].expression) for j, c in enumerate(coef) if c != 0.0]
    if not terms:
        return sympy.Integer(0)
    if ordered:
        terms = [t for t in terms if t.is_Number] + sorted((t for t in terms if not t.is_Number),
                                                           key=ADD_ORDER)
    return terms[0] if len(terms) == 1 else sympy.Add(*terms, evaluate=False)


@contextlib.contextmanager
def single_threaded_blas() -> Iterator[None]:
    """Small problems: BLAS threads only contend (measured 3-10x slower on 2 busy cores)."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # optional: installed with scikit-learn, which pyoperon needs
        yield
        return
    with threadpool_limits(limits=1, user_api="blas"):
        yield


class SparseEngine:
    """STLSQ over the candidate library (identification.library): fast, exact on library structures."""

    name = "sparse"

    def __init__(self, settings: SparseSettings | None = None):
        self.settings = settings or SparseSettings()
        self.features = build_library(self.settings.groups)
        self._nodes = [complexity(f.expression) for f in self.features]
        self.timings: dict[str, float] = {}
        self._cache: list[tuple[np.ndarray, np.ndarray]] = []
        self._compiled: Callable[[np.ndarray], np.ndarray] | None = None

    def _complexity(self, idx: np.ndarray) -> int:
        """complexity() of sparse_expression() without walking the tree."""
        total = 0
        for j in idx:
            feature = self.features[j].expression
            if feature == 1:
                total += 1
            elif isinstance(feature, sympy.Mul):
                total += self._nodes[j] + 1
            else:
                total += self._nodes[j] + 2
        return total + (1 if len(idx) > 1 else 0)

    def matrix(self, X: np.ndarray) -> np.ndarray:
        """The feature matrix of X (N,16), cached for the last few arrays seen."""
        for key, theta in self._cache:
            if key is X:
                return theta
        if self._compiled is None:
            self._compiled = compile_features(self.features)
        theta = self._compiled(X)
        self._cache = [(X, theta), *self._cache[:3]]
        return theta

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
        """Candidates of every size for one target (deterministic: seed and budget unused, the work is
        fixed by the settings)."""
        if loss not in LOSSES:
            raise ValueError(f"loss must be one of {LOSSES}")
        start = time.perf_counter()
        X = np.asarray(X, dtype=float)
        y = np.asarray(y, dtype=float)
        with single_threaded_blas():
            return self._fit(X, y, loss, progress, start)

    def _fit(
        self,
        X: np.ndarray,
        y: np.ndarray,
        loss: str,
        progress: Progress | None,
        start: float,
    ) -> list[Candidate]:
        theta = self.matrix(X)
        problem = LeastSquaresProblem(theta, y)
        sets = sparse_active_sets(
            problem, self.settings, progress, [f.group for f in self.features], self._nodes
        )
        candidates: list[Candidate] = []
        for i, active in enumerate(sets):
            coef = problem.solve(active)
            if loss == "absolute" and np.count_nonzero(active) <= self.settings.irls_max_terms:
                coef = problem.l1_refit(active, coef, self.settings.irls_iterations)
            expr = sparse_expression(self.features, coef)
            train = loss_fn(y, theta @ coef, loss)
            idx = np.flatnonzero(coef)
            cand = Candidate(
                expression=expr,
                complexity=self._complexity(idx),
                train_loss=train,
                engine=self.name,
                predict=lambda X_, idx=idx, c=coef[idx]: self.matrix(X_)[:, idx] @ c,
            )
            candidates.append(cand)
            if progress:
                progress(0.5 + 0.5 * (i + 1) / len(sets), f"{len(candidates)} candidates")
        self.timings = {"sparse": time.perf_counter() - start}
        return candidates
