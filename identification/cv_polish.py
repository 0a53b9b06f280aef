"""One-term moves from the pick, scored by cross-validation (SelectionSettings.cv_folds > 1).

The engine builds its candidates and polishes its pick against the pick rows (identification.discovery),
and the terms it found live in many candidates: genetic programming's shapes in one, the paths' in
another. On realistic-sensor fang-chen-aero's fy the pick had wz (u1^2 - u2^2 + u3^2 - u4^2) and a
constant (the accelerometer's bias); genetic programming had found wz (u1 - u2 + u3 - u4), but only in
candidates without the constant. Here the pick's terms are swapped one at a time for any term of any
candidate, removed, or one such term added; every move is scored by the same cross-validation as the
candidates (identification.cross_validation) and joins them, and the pick's own rule (identification.pareto:
identified on the fit and pick rows (SelectionSettings.identify_on_pick_rows), no anti-damping, the
simplest within tolerance of the best) picks again, until the pick stays (at most `rounds` times). The
moves are fitted on the fit rows, as the engine's candidates.
Beside every candidate's terms the moves may use `extra` terms: identify passes the engine's shape twins of
the pick's terms (DiscoveryEngine.nearest_features; SelectionSettings.cv_polish_twins), and the features
most correlated with the pick's cross-validated residual over the fit and pick rows
(DiscoveryEngine.residual_features; SelectionSettings.cv_polish_residual): the engine screens on the fit
rows alone, and a term only the pick rows excite is in none of its candidates; and each height term of the
pick without rotor speeds times the rotors' thrust sum (thrust_twins;
SelectionSettings.cv_polish_thrust_twins). On realistic-sensor fang-chen-aero (seed 2) fz held |wz| where
the true term is wz^2: the swap has the lower cross-validated loss (0.011039 against 0.011049), but no
candidate held wz^2, so no move could bring it in. More moves change the rotor speeds' family, in all terms
at once and in each cofactor's terms (rotor_power_twins): on realistic-sensor fang-chen-aero (seed 5) fy
held -2.67e-8 wz (u1^2 - u2^2 + u3^2 - u4^2), written as two terms, where the SITL's rotor drag is linear in
the speeds; no one-term move leaves that family. And each cofactor's rotor terms may be merged into the
mixer's sign pattern nearest their coefficients, alone or beside the rotors' sum (rotor_patterns): on
closed-loop realistic-sensor fang-chen-aero (seed 5) dwx held wz u2^2 and wz (u1^2 + u2^2 + u3^2 - u4^2)
(VIF 77), where the SITL has wz (u1 - u2 + u3 - u4) and a small common part; the merged pair has the lower
cross-validated loss and a VIF of 2.
Each round also moves on from up to `beam` models of the last round's moves that are better than the pick
and no larger, yet not picked (SelectionSettings.cv_polish_beam), best first: their one-term moves and
rotor-power twins are scored as the pick's, and any of them the rule can pick joins the candidates. The
rule rejects a model whose terms are tied (unidentified), and the way from the pick to a better model may
pass through such models: on realistic-sensor fang-chen-aero (seed 23) fy's pick held the rotors' sum for
the constant (the accelerometer's bias) and wx + wx (u1^2 + .. + u4^2) for wx (u1 + .. + u4); the true
structure, smaller and better, was several moves away, and every model between was better than the pick
and not identified (the rotors' sum, or its root, beside wx sum(u)), so a polish of the pick alone stopped.
While a candidate passes the identification rule, a move that keeps a set of terms whose VIF exceeds the
rule's limit (the model it moves from, or one of its one-term removals: tied_subsets) is left out unfitted:
a term's VIF only grows with the terms beside it, so no such move could be picked or set the tolerance.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Container, Iterable, Sequence

import numpy as np
import sympy

from identification.body_frame import PRIMITIVE_SYMBOLS
from identification.candidate import Candidate
from identification.collinearity import term_shapes
from identification.cross_validation import FoldedRows
from identification.engine_settings import SelectionSettings
from identification.feature_space import sign_patterns
from identification.metrics import loss as loss_fn
from identification.model_file import INPUT_NAMES, complexity
from identification.paired_loss import paired_loss_t
from identification.pareto import admissible, pick_best, select, terms_identified, within_tolerance
from identification.refit import terms_candidate
from identification.sparse import single_threaded_blas
from identification.weak_noise import column_scale


def thrust_twins(shapes: Sequence[sympy.Expr]) -> list[sympy.Expr]:
    """Each shape that reads the height h (m) and no rotor speed, times the rotors' thrust sum
    u1^2 + .. + u4^2 ((rad/s)^2): a ground effect scales the rotors' thrust, and on a flight near hover the
    bare law and the law times the thrust differ by little, so the screening takes the simpler one."""
    h = PRIMITIVE_SYMBOLS["h"]
    thrust = sympy.Add(*(PRIMITIVE_SYMBOLS[n] ** 2 for n in INPUT_NAMES))
    return [s * thrust for s in shapes if h in s.free_symbols and not _rotors(s)]


def model_size(shapes: Sequence[sympy.Expr]) -> int:
    """The complexity the engine gives a linear model of these terms (nodes, 2 per coefficient, 1 per sum)."""
    return sum(complexity(s) + (1 if s == 1 else 2) for s in shapes) + (1 if len(shapes) > 1 else 0)


def polish_by_cross_validation(
    chosen: Candidate,
    candidates: list[Candidate],
    folded: FoldedRows,
    kind: str,
    selection: SelectionSettings,
    mark: Callable[[list[Candidate]], None],
    rounds: int = 4,
    engine: str = "cv-polish",
    extra: Sequence[sympy.Expr] = (),
    beam: int = 0,
    all_tolerated: bool = False,
) -> Candidate:
    """The pick after up to `rounds` rounds of one-term moves (module docstring); the moves that could be
    picked (within the pick's tolerance of the best) are appended to `candidates`. mark: sets the new
    candidates' self-feedback (identification.self_feedback on the fit rows). extra: terms the moves may
    use beside every candidate's (the engine's shape twins of the pick's terms). beam: the models better
    than the pick, no larger and not picked, that each round also moves on from (0: the pick alone).
    all_tolerated: every move within the tolerance joins, also one more complex than the pick and no
    better (a later pick, identification.specification_pick, chooses among all of them)."""
    with single_threaded_blas():  # small solves: BLAS threads only contend
        return _polish(chosen, candidates, folded, kind, selection, mark, rounds, engine, extra, beam,
                       all_tolerated)


def _polish(chosen: Candidate, candidates: list[Candidate], folded: FoldedRows, kind: str,
            selection: SelectionSettings, mark: Callable[[list[Candidate]], None], rounds: int,
            engine: str, extra: Sequence[sympy.Expr] = (), beam: int = 0,
            all_tolerated: bool = False) -> Candidate:
    if chosen.holdout_loss is None or not np.isfinite(chosen.holdout_loss):
        return chosen  # nothing scored: no tolerance to compare moves against
    pool = move_pool(chosen, candidates, folded, extra)
    bits: dict[sympy.Expr, int] = {}  # each term's bit in the term sets' masks (_mask)
    # a set's mask does not depend on its terms' order, nor does any test on masks on which term got which bit
    seen = {_mask(c.linear[0] if c.build is not None else term_shapes(c.expression), bits)
            for c in candidates}
    scale = folded.scale
    expanded: set[frozenset[sympy.Expr]] = set()
    frontier: list[list[sympy.Expr]] = []
    tied: list[int] = []  # term sets the rows do not separate (bit masks): no superset is identified
    for _ in range(rounds):
        current = term_shapes(chosen.expression)
        states = [current, *[f for f in frontier if _key(f) != _key(current)][:beam]]
        # while a candidate passes the identification rule (the pick does), one that fails it is never
        # picked nor sets the tolerance: a move holding a tied set is left out unfitted (tied_subsets)
        ruled = admissible(chosen, selection)
        scored = []
        for state in states:
            if _key(state) in expanded:
                continue
            expanded.add(_key(state))
            expression = chosen.expression if state is current else None
            scored += _scored_moves(state, expression, pool, folded, kind, seen, bits)
            if ruled:
                tied += [_mask(t, bits) for t in tied_subsets(state, folded, selection)]
        # a move the pick can choose is within its tolerance of the best identified loss, which is at most
        # the current pick's (whether a move is identified is measured only when the pick asks), and not
        # worse than the pick beyond the rows' noise
        limit = within_tolerance(float(chosen.holdout_loss), selection, scale)
        base, z = folded.predictions(current), selection.cv_polish_z
        eligible = [(value, shapes) for value, shapes in scored if value <= limit
                    and not (ruled and tied and _holds_any(_mask(shapes, bits), tied))]
        if ruled:
            new = _pickable_moves(eligible, candidates, pool, folded, kind, selection, mark, engine, base,
                                  float(chosen.holdout_loss), None if all_tolerated else chosen.complexity)
        else:
            new = [c for value, shapes in eligible
                   if not _worse(folded, shapes, base, value, float(chosen.holdout_loss), kind, z)
                   and (c := move_candidate(shapes, value, folded, kind, engine)) is not None]
            mark(new)
        if new:
            candidates.extend(new)
            chosen = select(candidates, selection, scale=scale, by_degree=True)
        # better than the pick and no larger, yet not picked (tied terms, unidentified): the way to a better
        # model the rule can pick may pass through it, so its moves are tried next
        picked = term_shapes(chosen.expression)
        size, loss_now, key_now = model_size(picked), float(chosen.holdout_loss), _key(picked)
        frontier = [shapes for value, shapes in sorted(scored, key=lambda vs: vs[0])
                    if value < loss_now and model_size(shapes) <= size and _key(shapes) not in expanded
                    and _key(shapes) != key_now]
        if key_now in expanded and not frontier[:beam]:
            return chosen
    return chosen


def move_pool(chosen: Candidate, candidates: Sequence[Candidate], folded: FoldedRows,
              extra: Sequence[sympy.Expr] = ()) -> dict[sympy.Expr, sympy.Expr]:
    """The terms the moves from `chosen` may use, each its own key: every candidate's and `extra`, one per
    column of values up to sign over folded's rows (the pick's own terms first; twins only make ties), all
    joined to folded's pool."""
    pool: dict[sympy.Expr, sympy.Expr] = {}  # sympy expressions hash by structure
    for c in candidates:
        for s in new_shapes(c, pool):
            pool[s] = s
    for s in extra:
        pool.setdefault(s, s)
    distinct: dict[bytes, sympy.Expr] = {}
    for s in [*term_shapes(chosen.expression), *pool]:
        distinct.setdefault(_values_up_to_sign(folded.column(s)), s)
    pool = {s: s for s in distinct.values()}
    folded.extend(list(pool.values()))
    return pool


def _values_up_to_sign(column: np.ndarray) -> bytes:
    """A term's values (M,) as bytes, negated when its first nonzero value is negative: a term and its
    negation (u1^2 - u2^2 beside u2^2 - u1^2, as two candidates wrote one rotor pattern) are one column to
    a linear model, and their moves tie exactly, so that rounding chose which of two equal moves was taken
    (closed-loop racer, seed 97: the polish's path turned there)."""
    nonzero = np.flatnonzero(column)
    flipped = nonzero.size > 0 and column[nonzero[0]] < 0
    return ((0.0 - column if flipped else column) + 0.0).tobytes()  # + 0.0: no -0.0 entries


def new_shapes(c: Candidate, known: Container[sympy.Expr]) -> list[sympy.Expr]:
    """A candidate's terms not in `known`, in the order its expression writes them (term_shapes). A move
    whose expression is not built yet (Candidate.build) is read from its fitted terms when at most one of
    them is new (then their order does not matter): a later polish reads every earlier move's terms, and
    building their sums was most of what reading them cost (seed 71's heavy closed loop's wx': 3,875 of
    3,981 moves)."""
    if c.build is not None and c.linear is not None:
        new = [s for s in dict.fromkeys(c.linear[0]) if s not in known]
        if len(new) <= 1:
            return new
    return [s for s in term_shapes(c.expression) if s not in known]


def _pickable_moves(eligible: list[tuple[float, list[sympy.Expr]]], candidates: Sequence[Candidate],
                    pool: dict[sympy.Expr, sympy.Expr], folded: FoldedRows, kind: str,
                    selection: SelectionSettings, mark: Callable[[list[Candidate]], None], engine: str,
                    base: np.ndarray, current: float, size: int | None) -> list[Candidate]:
    """The moves (cross-validated loss, terms) the pick could ever take, fitted and marked, where the pick
    passes its rule: those within the tolerance of the best loss the rule passes once they join. The moves
    are fitted lowest loss first; the first the rule passes sets that best if it lowers it, and no move
    above its tolerance is fitted. That best only falls as candidates join, so such a move is never picked
    nor sets the tolerance (the pick is the same; closed-loop heavy-650-aero's wx', 58 terms: 6,136 moves
    fitted and marked, where fitting every move within the current pick's tolerance fitted 11,475; 2,577
    are within the final tolerance). The rule measures the moves below the first that passes, as the pick's
    own rule does. Nor is a move fitted that is more complex than the pick (complexity `size`, its loss
    `current`; None: such moves are fitted too) and no better: the pick passes the rule, and is within the
    tolerance wherever such a move is, ahead of it, so the pick or a candidate before it is chosen (seed 41's
    heavy closed loop's wx': 7,616 -> 5,928 moves fitted, the same model, 117 -> 110 s). A move holding a
    term of no candidate (a rotor-power twin, a rotor pattern) is fitted as before: the specification search
    draws its terms from the candidates."""
    z = selection.cv_polish_z
    best = pick_best(candidates, selection)
    cutoff = within_tolerance(best, selection, folded.scale)
    new: list[tuple[int, Candidate]] = []
    tail: int | None = None  # from here on the moves are not marked yet: the best the rule passes is final
    for at in sorted(range(len(eligible)), key=lambda k: eligible[k][0]):
        value, shapes = eligible[at]
        if (value > cutoff or (size is not None and value >= current and model_size(shapes) > size)) \
                and all(t in pool for t in shapes):  # no term of no candidate
            continue
        if _worse(folded, shapes, base, value, current, kind, z):
            continue
        c = move_candidate(shapes, value, folded, kind, engine)
        if c is None:
            continue
        new.append((at, c))
        if tail is not None:
            continue
        if value >= best:  # this move and the rest (no lower) cannot lower the best
            tail = len(new) - 1
            continue
        mark([c])
        if admissible(c, selection):
            best, tail = value, len(new)
            cutoff = within_tolerance(best, selection, folded.scale)
    if tail is not None:
        mark([c for _, c in new[tail:]])
    return [c for _, c in sorted(new, key=lambda ac: ac[0])]  # in the moves' order, as all were before


def tied_subsets(state: list[sympy.Expr], folded: FoldedRows,
                 selection: SelectionSettings) -> list[frozenset[sympy.Expr]]:
    """The model `state` and each of its one-term removals whose largest VIF on the rows the pick measures
    on (FoldedRows.identification) fails the pick's VIF rule (above max_vif, its weakest t ratio short of
    what that VIF asks: pareto.terms_identified); none when the model's own passes. A term's VIF only
    grows with the terms beside it (its regression on more columns explains at least as much) and its
    standard error with it, so a move that keeps such a set fails the rule too (nearly always: on rows with
    no stated noise a term added may lower the residual, the noise behind the t ratios). A pick its engine
    did not measure (the library engine's) may hold a tied family: on an ArduCopter flight near hover with
    the yaw held, az held 24 thrust terms times products of sin and cos of the angles, where cos(psi)
    barely varies; its one-term swaps, some 11,700 within the pick's tolerance and each tied, were fitted
    and measured one by one (`quadsr identify --targets az` on that flight: 211 s wall, 30 s with them left
    out, the same model)."""
    def tied(shapes: list[sympy.Expr]) -> bool:
        t, vif = folded.identification(shapes)
        return vif is not None and vif > selection.max_vif and not terms_identified(t, vif, selection)

    if not tied(state):
        return []
    out = [_key(state)]
    for i in range(len(state)):
        rest = state[:i] + state[i + 1:]
        if rest and tied(rest):
            out.append(_key(rest))
    return out


def _mask(shapes: Iterable[sympy.Expr], bits: dict[sympy.Expr, int]) -> int:
    """The terms as a bit mask, each term's bit given on first sight (subset tests over many moves)."""
    m = 0
    for s in shapes:
        m |= bits.setdefault(s, 1 << len(bits))
    return m


def _holds_any(mask: int, subsets: list[int]) -> bool:
    """Whether the mask holds every bit of any of the subsets' masks."""
    return any(t & mask == t for t in subsets)


def _scored_moves(current: list[sympy.Expr], expression: sympy.Expr | None,
                  pool: dict[sympy.Expr, sympy.Expr], folded: FoldedRows, kind: str,
                  seen: set[int], bits: dict[sympy.Expr, int]) -> list[tuple[float, list[sympy.Expr]]]:
    """(cross-validated loss, terms) of each move from the model `current` not seen before, with a finite
    loss: one-term moves over the pool, rotor-power twins and, given its fitted `expression`, rotor
    patterns; seen (term sets as _mask's masks over bits) is updated."""
    have = set(current)
    others = [p for p in pool.values() if p not in have]
    folded.include(current)
    batch = folded.move_losses(current, others, kind)  # the one-term moves' losses at once
    moves = _moves(current, others)
    known = _batch_values(batch, len(current), len(others), len(moves))
    keys = _move_masks(current, others, bits)
    moves += rotor_power_twins(current)
    if expression is not None:
        moves += rotor_patterns(expression, current)
    keys += [_mask(shapes, bits) for shapes in moves[len(keys):]]
    scored = []
    for m, shapes in enumerate(moves):
        key = keys[m]
        if key in seen:
            continue
        seen.add(key)
        # inf from the batch: the move's new term is a combination of the terms it joins (the polish had
        # refit each such move alone, some 500 a round on a closed-loop wx', for a loss no pick could take)
        value = known[m] if m < len(known) and not np.isnan(known[m]) else (
            folded.terms_loss(shapes, kind) if shapes else float("inf"))
        if np.isfinite(value):
            scored.append((value, shapes))
    return scored


def _worse(folded: FoldedRows, shapes: list[sympy.Expr], base: np.ndarray, value: float, current: float,
           kind: str, z: float) -> bool:
    """Whether a move's cross-validated predictions are worse than the pick's (base) by more than z paired
    standard errors over the folds' blocks (identification.paired_loss); never with z 0 or a lower loss."""
    if z <= 0.0 or value <= current:
        return False
    return bool(paired_loss_t(folded.y, folded.predictions(shapes), base, kind, folded.blocks) > z)


def _key(shapes: Sequence[sympy.Expr]) -> frozenset[sympy.Expr]:
    return frozenset(shapes)


def _moves(current: list[sympy.Expr], others: list[sympy.Expr]) -> list[list[sympy.Expr]]:
    """Each term removed, swapped for a term of others (not in current), and each of others added."""
    out = [current[:i] + current[i + 1:] for i in range(len(current))]
    out += [current[:i] + [p] + current[i + 1:] for i in range(len(current)) for p in others]
    out += [[*current, p] for p in others]
    return out


def _move_masks(current: list[sympy.Expr], others: list[sympy.Expr],
                bits: dict[sympy.Expr, int]) -> list[int]:
    """_mask of each of _moves(current, others), in its order, from the masks of current's terms and of
    others' (a swap: current's mask less one term's bit, one other's bit added), where _mask would visit
    every term of each of some 100,000 moves (current's terms distinct, others none of them)."""
    if len(set(current)) != len(current):  # a repeated term: a removal may keep its bit
        return [_mask(shapes, bits) for shapes in _moves(current, others)]
    own = [_mask([t], bits) for t in current]
    extra = [_mask([p], bits) for p in others]
    whole = _mask(current, bits)
    out = [whole & ~b for b in own]
    out += [(whole & ~b) | e for b in own for e in extra]
    out += [whole | e for e in extra]
    return out


def _batch_values(batch: tuple[np.ndarray, np.ndarray] | None, k: int, count: int, moves: int) -> np.ndarray:
    """The losses FoldedRows.move_losses gave, in _moves' order (NaN: the removals, and what the batch
    left to terms_loss; inf: a move whose new term is a combination of those it joins, not scored)."""
    if batch is None:
        return np.full(moves, np.nan)
    swaps, adds = batch
    return np.concatenate([np.full(k, np.nan), swaps.reshape(k * count), adds])


def rotor_power_twins(current: list[sympy.Expr]) -> list[list[sympy.Expr]]:
    """The model with every rotor speed's square lowered to the speed, and with every speed raised to its
    square, in all its terms at once and in the terms of each cofactor apart (each move when it changes the
    model). Rotor speeds vary a few per cent about hover, so u_i and u_i^2 are near twins in every product
    (u^2 = ubar^2 + 2 ubar d + d^2), and a model written in one family is only reached from the other by
    moving several terms together; the cofactor (a term's factors without a rotor speed: wz for
    wz (u1^2 - u2^2), 1 for u1^2) keeps a moment's thrust terms apart from its rotor drag."""
    groups: dict[sympy.Expr, list[int]] = {}
    for i, t in enumerate(current):
        if _rotors(t):
            groups.setdefault(_cofactor(t), []).append(i)
    selections = [list(range(len(current)))] + (list(groups.values()) if len(groups) > 1 else [])
    out: list[list[sympy.Expr]] = []
    for chosen in selections:
        for lower in (True, False):
            terms = list(current)
            for i in chosen:
                terms[i] = _power_twin(current[i], lower)
            if _key(terms) != _key(current) and len(set(terms)) == len(terms) and terms not in out:
                out.append(terms)
    return out


def rotor_patterns(expression: sympy.Expr, current: list[sympy.Expr]) -> list[list[sympy.Expr]]:
    """The model with each cofactor's rotor terms (two or more rotors' speeds at one power, read from the
    fitted `expression` of the terms `current`) replaced by the mixer's sign pattern nearest their per-rotor
    coefficients, alone and beside the rotors' sum, at that power and the other. A symmetric vehicle's
    effects enter through its mixer's patterns (collective, roll, pitch, yaw: u1 + u2 + u3 + u4, ...), and
    a model that split one into several terms is only reached back by moving them together."""
    names = {x.name: x for x in expression.free_symbols if isinstance(x, sympy.Symbol)}
    rotors = [names.get(n, sympy.Symbol(n)) for n in INPUT_NAMES]
    groups: dict[tuple[sympy.Expr, int], np.ndarray] = {}
    for coef, shape in _terms(expression):
        if not _rotors(shape):
            continue  # nothing of a rotor's: its expansion (a height law's can be long) adds no group
        for mono, c in _expanded(shape):
            key = _rotor_power(mono)
            if key is not None:
                x, p = key
                cof = _cofactor(mono)
                groups.setdefault((cof, p), np.zeros(len(rotors)))[rotors.index(x)] += float(coef * c)
    patterns = [np.array(signs, float) for signs in sign_patterns(len(rotors))]
    total = patterns[0]  # the rotors' sum
    membership = {t: _group(t) for t in current}  # each term expanded once, not once per group
    out: list[list[sympy.Expr]] = []
    for (cof, p), c in groups.items():
        if np.count_nonzero(c) < 2:
            continue
        alone = max(patterns, key=lambda s: abs(float(c @ s)))
        centred = c - c.mean()  # the part the sum leaves: the pattern beside the sum is fitted to it
        beside = max(patterns[1:],
                     key=lambda s: abs(float(centred @ (s - s.mean()))) / np.linalg.norm(s - s.mean()))
        keep = [t for t in current if membership[t] != (cof, p)]
        for signs in ([alone], [beside, total]):
            for q in (p, 3 - p):
                terms = [*keep, *(cof * sympy.Add(*[int(k) * x**q for k, x in zip(s, rotors, strict=True)])
                                  for s in signs)]
                if _key(terms) != _key(current) and len(set(terms)) == len(terms) and terms not in out:
                    out.append(terms)
    return out


def _terms(expression: sympy.Expr) -> list[tuple[sympy.Expr, sympy.Expr]]:
    """(coefficient, shape) of each additive term of an expression, nested sums walked."""
    out, stack = [], [expression]
    while stack:
        e = stack.pop()
        if e.is_Add:
            stack.extend(reversed(e.args))
        else:
            out.append(e.as_coeff_Mul())
    return out


@functools.lru_cache(maxsize=4096)
def _expanded(shape: sympy.Expr) -> tuple[tuple[sympy.Expr, sympy.Expr], ...]:
    """The monomials of a term's expansion with their coefficients, each over the term's denominator as it
    stands (cached: the polish's rounds and targets share terms, and expanding them was 2-3 % of a
    closed-loop fit's CPU). The numerator alone is expanded: sympy.expand also multiplies out a power of a
    sum in the denominator, a hub law's 1/H_i^k (H_i = h - r_i . g) into a polynomial of 15-35 terms, which
    was 3.3 of 24 s of the polish of the heavy closed loop's wx' (seed 71, pyinstrument) and tells the rotors
    no better apart: each rotor's H_i is its own either way. A sum (the law as one term) is expanded term by
    term."""
    if shape.is_Add:
        merged: dict[sympy.Expr, sympy.Expr] = {}
        for arg in shape.args:
            for m, c in _expanded(arg):
                merged[m] = merged.get(m, 0) + c
        return tuple((m, c) for m, c in merged.items() if c != 0)
    numerator, denominator = sympy.fraction(shape)
    return tuple((m / denominator, c) for m, c in sympy.expand(numerator).as_coefficients_dict().items())


def _rotor_power(mono: sympy.Expr) -> tuple[sympy.Symbol, int] | None:
    """(the rotor speed, its power 1 or 2) of a monomial with one rotor speed, else None."""
    family = _rotors(mono)
    if len(family) != 1:
        return None
    x = next(iter(family))
    p = mono.as_powers_dict().get(x, 0)
    return (x, int(p)) if p in (1, 2) else None


@functools.lru_cache(maxsize=4096)
def _group(term: sympy.Expr) -> tuple[sympy.Expr, int] | None:
    """(cofactor, power) when every monomial of the term is one rotor speed at that power times that
    cofactor, else None."""
    keys = set()
    for m, _ in _expanded(term):
        k = _rotor_power(m)
        if k is None:
            return None
        keys.add((_cofactor(m), k[1]))
    return next(iter(keys)) if len(keys) == 1 else None


def _rotors(term: sympy.Expr) -> set[sympy.Symbol]:
    """The rotor speeds (rad/s) the term holds."""
    return {x for x in term.free_symbols if isinstance(x, sympy.Symbol) and x.name in INPUT_NAMES}


def _cofactor(term: sympy.Expr) -> sympy.Expr:
    """The term's factors that hold no rotor speed (1 when none)."""
    return sympy.Mul(*[f for f in sympy.Mul.make_args(term) if not _rotors(f)]).as_coeff_Mul()[1]


def _power_twin(term: sympy.Expr, lower: bool) -> sympy.Expr:
    """The term with its rotor speeds' squares lowered, or its (first-power) speeds raised to squares."""
    family = _rotors(term)
    if lower:
        return term.xreplace({sympy.Pow(x, 2): x for x in family})
    if any(isinstance(a, sympy.Pow) and a.base in family for a in sympy.preorder_traversal(term)):
        return term  # a term with a power of a speed is not raised
    return term.xreplace({x: x**2 for x in family})


def _fit_rows_loss(folded: FoldedRows, shapes: list[sympy.Expr], coef: np.ndarray, kind: str) -> float:
    """The loss of the terms with these coefficients on the fit rows (a move's training loss)."""
    a, y, _lag = folded.fit_part(shapes)
    return loss_fn(y, a @ coef, kind)


def move_candidate(shapes: list[sympy.Expr], cv_loss: float, folded: FoldedRows, kind: str,
               engine: str) -> Candidate | None:
    """A move fitted (least squares) on the fit rows, its held-out loss the cross-validated one, its training
    loss computed when read (Candidate.trained), its t ratios and VIF measured when the pick asks
    (FoldedRows.identification: on the fit and pick rows, or the fit rows alone), its expression built when
    read (most moves' never are); None when its expression would not read back as its terms (a term twice,
    or a zero coefficient, which the sum leaves out)."""
    # from the prepared normal equations: a 58-term move on 11,850 rows 0.06 ms against lstsq's 10.7 ms (one
    # thread); seed 41's heavy closed loop's wx' solves 5,800 moves. Else lstsq, on unit-RMS columns: its
    # cutoff is relative to the largest singular value, and on the raw columns (RMS 0.16 to 6e11) it dropped
    # 6-9 of 29 terms' directions (119 of those moves read an RMS error of 0.13-0.39 rad/s^2 for 2.1e-5)
    coef = folded.fit_coefficients(shapes)
    if coef is None:
        a, y, _lag = folded.fit_part(shapes)
        size = column_scale(a)
        coef = np.linalg.lstsq(a / size, y, rcond=None)[0] / size
    # the read-back test without the expression: on seed 71's heavy closed loop's wx' it gave the same
    # answer as reading back the built sum for all 3,981 moves (session 72)
    if len(set(shapes)) != len(shapes) or np.any(coef == 0.0):
        return None
    c = terms_candidate(shapes, coef, engine, ordered=True, lazy=True)  # read back without rebuilding the sum
    c.complexity, c.holdout_loss = model_size(shapes), cv_loss
    c.train = functools.partial(_fit_rows_loss, folded, shapes, coef, kind)
    c.measure = lambda: folded.identification(shapes)
    return c
