"""The engine settings (YAML: identify --settings FILE; every key optional), typed and validated.

Kept apart from the engines and the registry so that both can import them (no import cycle).
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bridge.errors import UserError
from bridge.yaml_file import Section, load_yaml_file, read_dataclass
from identification.library import DEFAULT_GROUPS, GROUPS

POLISH_RULES = ("occam", "tolerance", "margin")  # DiscoverySettings.polish_rule
SETTINGS_HINT = "every key is optional; see the dataclasses in identification/engine_settings.py"


@dataclass(frozen=True)
class SparseSettings:
    """Sequentially thresholded least squares over the candidate library."""

    groups: tuple[str, ...] = DEFAULT_GROUPS  # library groups (identification.library)
    thresholds: int = 40  # points of the threshold sweep (log-spaced)
    threshold_min: float = 1e-7  # smallest term contribution kept (coef * feature std / target std)
    threshold_max: float = 0.5
    max_iterations: int = 25  # STLSQ iterations per threshold
    backward: bool = True  # also the backward-elimination path (every model size)
    forward_terms: int = 25  # also greedy forward selection up to this many terms (0: off)
    swap_max_terms: int = 8  # forward sets up to this size also try each term's simpler same-group terms
    irls_iterations: int = 10  # absolute-error refit (loss: absolute); each stops at <0.1% gain
    irls_max_terms: int = 24  # larger candidates (overfits, the held-out yardstick) stay least squares


@dataclass(frozen=True)
class OperonSettings:
    """pyoperon's NSGA-II genetic programming (objectives r2 and length: a real Pareto front)."""

    population_size: int = 500  # generations: the identify budget (an iteration count, no time cap)
    max_length: int = 40
    max_depth: int = 10
    optimizer_iterations: int = 10  # constant fitting (0 would turn it off)
    n_threads: int = 2
    allowed_symbols: str = "add,sub,mul,div,sin,cos,constant,variable"
    engineered_inputs: bool = True  # f1..f4, g, the thrust directions and cos(phi)cos(theta) as inputs


@dataclass(frozen=True)
class PysrSettings:
    """PySR (Julia) behind the same interface."""

    populations: int = 8  # iterations: the identify budget
    maxsize: int = 30
    binary_operators: tuple[str, ...] = ("+", "-", "*", "/")
    unary_operators: tuple[str, ...] = ("sin", "cos")
    probe_timeout_s: float = 60.0
    engineered_inputs: bool = True


@dataclass(frozen=True)
class DiscoverySettings:
    """The discovery engine (identification.discovery): features grown from body-frame primitives.

    Budgets are counts (rungs, screened features, rounds; the GP's generations are identify's budget), never
    seconds.
    """

    # gx, gy: the gravity direction FRD (the ground plane's normal), used only in the ground-plane gradients
    # of a height law (identification.feature_space "tilt"), for a flight near the ground
    primitives: tuple[str, ...] = (
        "ub", "vb", "wb", "wx", "wy", "wz", "u1", "u2", "u3", "u4", "h", "gx", "gy",
    )
    operators: tuple[str, ...] = ("mul", "pow", "abs", "inv", "tilt", "norm", "sincos", "add")
    # 1/x of a positive primitive (the height) only where its smallest value on the fit rows is at least its
    # median / inverse_span (identification.feature_space): a lift-off's rows at h -> 0 would own 1/h^2
    inverse_span: float = 10.0
    # 1/x .. 1/x^inverse_powers of such a primitive for a flight far from the ground: on the README's
    # paper-train flight (h 70-200 m) 4 crowded the screening and the pick took u4^2/h for the thrust
    inverse_powers: int = 2
    # .. 1/x^near_inverse_powers, and the ground-plane gradients, for a flight that reaches near the ground on
    # its own scale: lowest height <= near_spread standard deviations of its heights (feature_space)
    near_inverse_powers: int = 3
    near_spread: float = 1.0
    # |x| only where x takes both signs: the smaller side's extent at least this share of the larger
    # (identification.feature_space); otherwise |x| = +-x on nearly every row and x stands for it
    abs_sign_share: float = 0.05
    # no feature of a positive primitive (the height) whose relative spread std/mean on the fit rows is below
    # this: a flight at 10 +- 0.05 m cannot tell h vb^2 from vb^2 (identification.feature_space.barely_varies)
    min_spread: float = 0.01
    rungs: int = 2  # 1: the unary features alone; 2: products/quotients of two; 3: of three (beam-grown)
    screen: int = 60  # features added to the pool per round by sure independence screening
    beam: int = 40  # rung-2 features (best screened) that are grown into rung 3
    rounds: int = 8  # at most this many screen -> sparsify -> residual rounds
    patience: int = 2  # stop after this many rounds in a row without a better held-out pick (0 acts as 1)
    max_terms: int = 20  # forward-selection path length in the sparsifier; larger models are not kept
    # ... unless a round's pick holds max_terms terms: the paths then grow by max_terms / 2 a time, up to
    # this many (the physics, not the budget, says how many terms a target has: a heavy vehicle with a CG
    # offset and every aerodynamic effect has 36 in its wx'; session 63)
    max_terms_limit: int = 60
    # each round, one more forward path that starts from the last round's pick (its terms in the pool) and
    # adds the pool's features to it, never a height feature: a height law is fitted as a whole, by the paths
    # from no terms (identification.sparse.forward_path initial=). The paths from no terms re-choose every
    # term and on a noisy flight run out of steps before the small ones (session 13, realistic-sensor
    # fang-chen-aero's wy': u_i wz, vb wx, ub wy found, 130/9/0 -> 132/7/4: fy's u_i wz taken as u_i^2 wz;
    # ideal fang-chen-aero's largest error 4.8 % -> 2.6 %; every other bench case the same). Adding height
    # features too took closed-loop fang-chen-aero 132/11/0 -> 128/15/1 (the 1/h series held u_i wz).
    forward_from_pick: bool = True
    thresholds: int = 12  # points of the sparsifier's STLSQ threshold sweep (at most sparse.thresholds)
    operon_population: int = 100  # genetic programming on the sparse model's residual, always run, for
    # `budget` generations (identify's --budget)
    operon_max_length: int = 15
    operon_optimizer_iterations: int = 5
    operon_threads: int = 1
    # the GP proposes shapes (its expressions come back as terms refit on every fit row), so it may read only
    # this many fit rows, evenly strided over the flight; 0 (the default): every fit row. Its cost is per
    # row. Measured with 4096 (session 14, bench/settings/gp-rows.yaml): CPU -18 to -40 % on the SITL cases
    # (closed-loop fang-chen-aero 101 -> 83 s), every case's structure the same but two already failing
    # (closed-loop aero 132/11/0 -> 132/11/1, realistic-sensor aero weak 132/7/4 -> 132/7/6): off by default
    operon_rows: int = 0
    # term-substitution polish of the pick (identification.discovery DiscoveryEngine._polish): at most this
    # many passes, each refitting the best polish_tries single-term swaps (ranked by least squares); 0: off.
    # With session 7's rule ("margin") it fixed sitl fang-chen-aero's structure (139/0/0) but took noise-level
    # swaps elsewhere (closed-loop aero 17 -> 19 extra, realistic-sensor aero 11 -> 23); with "occam"
    # (session 8, same flights): fang-chen-aero 139/0/0, closed-loop aero 17 extra (3.25 -> 1.77 %),
    # realistic-sensor aero (weak form) 124/13/11 -> 127/10/7, every regression case unchanged
    polish_passes: int = 3
    polish_tries: int = 12
    # which moves the polish takes (POLISH_RULES; DiscoveryEngine._polish). "occam": a move whose pick-row
    # loss is lower than the current model's by more than polish_z standard errors (paired differences, the SE
    # from polish_blocks contiguous blocks' means) and that adds no complexity (see polish_grow); else the
    # simplest swap or one-term removal that lowers the complexity, is not worse by more than polish_z
    # standard errors and stays within the pick's tolerance of the best pick loss.
    # "tolerance": the pick's rel_tol/abs_tol alone for both (measured: gives wz^2's slot to |wz| on
    # noise-free aero data). "margin" (session 7): any swap whose pick loss is lower by > 0.1 %
    polish_rule: str = "occam"
    polish_z: float = 2.0
    polish_blocks: int = 20
    # "occam" only: also take a better move that raises the complexity, when it beats the current model by the
    # pick's tolerance too (measured: on closed-loop aero it wrote fz's wz^3 as wz^2 (u1^2+..+u4^2), 3 extras)
    polish_grow: bool = False
    # split moves: one term of the pick replaced by two pool features, the pairs among each term's
    # polish_split_width best single swaps (term_splits), the polish_tries best refitted and taken as grows
    # (better by polish_z standard errors and by the pick's tolerance); below 2: off. A term standing for a
    # sum of two true ones (|wx| |wy| for wx^2 + wy^2) is a local optimum of one-term swaps
    polish_split_width: int = 30
    # one more polish move: the model with its constant toggled (in <-> out), taken as a grow
    polish_constant: bool = True
    # one more kind of polish move (occam rule): two of the model's terms joined into one pool feature
    # (term_merges, the splits' inverse), taken as the simpler moves are: not worse by polish_z standard
    # errors and within the pick's tolerance (realistic-sensor fang-chen-aero's wy': |vb| + vb^2 |vb| -> vb^2)
    polish_joins: bool = True
    # merge repair (DiscoveryEngine._merge_repair): when the pick without the VIF rule (the t rule kept) is a
    # model the VIF rule sets aside, two of its terms merged into one feature of the space (the polish_tries
    # best merges by least squares, term_merges), kept when it passes the rules and is not worse than that
    # model by more than polish_z standard errors nor beyond the pick's tolerance; the VIF of a term among
    # combinations of one family depends on how they are written (closed-loop aero's dwz: wz (u1+u2+u3+u4)
    # + u2 wz + u4 wz + wz, VIF 199, is wz (u1+u2+u3+u4) + wz (u1-u2+u3-u4) + wz, VIF 36, the true structure)
    polish_merge: bool = True
    # hub law (identification.hub_law): for a flight near the ground, where the rounds would stop with height
    # terms in the pick, they are refit as one law per target at each rotor's hub height h - r_i.g, the hubs'
    # offsets r_i learned (variable projection, at most hub_law_evaluations function evaluations per stage:
    # from the CG the in-plane arms, then all twelve offsets), powers of
    # 1/H_i up to hub_law_powers; the law joins the pool as one feature in place of the height features,
    # and rounds go on on its residual; at most hub_law_fits times (0: off). On by default since session 20,
    # with hub_law_shared (below): over the whole discovery bench it changes two cases, both for the better
    # (sitl ground effect 36/0/1 -> 36/0/0, closed-loop fang-chen-aero 134/9/0 -> 137/6/0; README). A law per
    # rotor (hub_law_shared false) had made sitl ground effect 36/0/1 (a wx' constant) and closed-loop aero's
    # wy' law 25 % off, which is why it was opt-in before
    # (the law is fitted beside the pick's terms and the screening pool's features without the height:
    # closed-loop aero then 142/1/2; docs/discovery-log.md, session 20). 2 since session 21: the law is refit
    # once beside the pick the first law's rounds reached (with hub_law_refit_airspeed below), the refit's
    # rounds kept only on evidence against that pick
    hub_law_fits: int = 2
    hub_law_powers: int = 4
    # the law is kept only when the pick its rounds reach beats the pick the series had reached on the pick
    # rows by more than polish_z standard errors (paired, polish_blocks blocks); else the series' model stays
    hub_law_evidence: bool = True
    hub_law_evaluations: int = 400
    # the law also holds each hub's squared in-plane airspeed (v_b + w x r_i, body x-y) per power of 1/H_i:
    # the ground multiplies a rotor's whole thrust, and that grows with its airspeed (translational lift).
    # Off by default, measured (session 12, README): on closed-loop fang-chen-aero the laws of fz and dwx
    # 0.39/1.71 % -> 0.28/0.24 %, but dwy 4.90 -> 5.20 %, the structure 137/6/1 -> 136/7/4, CPU +23 %
    # Session 20, the shared law fitted beside the pool: closed-loop aero 142/1/2, 6.4 % -> 142/1/0, 4.97 %
    # (laws 0.12/0.14/0.20 %), but sitl ground effect (no translational lift) 36/0/0 -> 36/0/3 (fz ub^2,
    # vb^2, wx' ub): off
    hub_law_airspeed: bool = False
    # a law refit (the second and later of hub_law_fits, beside the pick the last law's rounds reached) holds
    # the airspeed part; its rounds are kept only when their pick beats that pick on the pick rows by more
    # than polish_z standard errors (hub_law_evidence), so a vehicle without translational lift keeps the
    # law it had. Session 21: closed-loop fang-chen-aero 142/1/2, 6.4 % -> 142/1/0, 2.85 %, sitl ground
    # effect 36/0/0 either way
    hub_law_refit_airspeed: bool = True
    # one law for every rotor (identical rotors), each rotor's share its moment arm about the CG from the
    # fitted offsets: 1 for a force (fx, fy, fz), -r_iy for wx', r_ix for wy' (r x F of a thrust along -z,
    # FRD; dwz keeps a law per rotor). K coefficients in place of 4K: a law per rotor was free to take up
    # other effects that differ from rotor to rotor (closed-loop fang-chen-aero: wy''s law 25 % off).
    hub_law_shared: bool = True
    # each rotor's share in the shared law: "thrust", the pick's own far-field coefficient of u_i^2 in the
    # target (the ground multiplies each rotor's own thrust, so a weaker rotor's share is smaller and a torque
    # target's share carries the rotor's arm as the data give it), or "arms" (the fitted hubs' arms, one
    # thrust for every rotor; the rule before session 64, and the rule where the pick holds no u_i^2 term)
    hub_law_shares: str = "thrust"
    # no law whose hub comes nearer the ground than this fraction of the CG's height at some row of the fit
    # rows: its 1/H_i^k columns are then a spike there that fits the target's errors, not a ground effect
    # (identification.hub_law.MIN_HUB_HEIGHT_FRACTION; a stage of the fit stops at the first iterate that
    # gets there and the fit gives no law, and the rounds end as they would with no law; 0: any hub above the
    # ground). Session 31: on the five realistic-sensor flights of the bench the laws went to hubs at
    # 0.0-0.13 of the CG's height and were then not kept; the true hubs stay above 0.8 of it on the bench's
    # truth flights (README, "Hubs at the ground")
    hub_law_min_height: float = 0.25
    # a last stage of each hub law's fit divides its parts by D_i = 1 - d1/H_i - d2/H_i^2 and refits the hubs
    # with d1 and d2 (identification.hub_law, "A law that is not a series"): a series in 1/H_i stops at
    # hub_law_powers, and its truncation moved the hubs (seed 71's heavy closed loop: 0.3 mm off, 7x the
    # targets' rounding left on wx' at the true hubs). Session 72
    hub_law_rational: bool = True


VIF_RULES = ("scaled", "cap")  # SelectionSettings.vif_rule


@dataclass(frozen=True)
class SelectionSettings:
    """The pick on held-out data: the smallest candidate with loss <= best*(1+rel_tol) + abs_tol*std(y)."""

    rel_tol: float = 0.02
    # of the held-out target's spread: the truth targets' float32 rounding (identification.pareto; 1e-6
    # until session 44, when the targets' step means carried 3e-5 m/s^2 of error)
    abs_tol: float = 1e-7
    # a candidate with a term whose t ratio is below min_t on the fit rows (collinearity.weakest_t; measured
    # beside a constant offset when the candidate has none) is not identified by the flight, and not picked
    # while an identified one exists (pareto.select)
    min_t: float = 5.0
    # on weak rows whose log states its targets' noise (Dataset.target_noise: our .tlog's step rows), those
    # t ratios use each term's standard error under that noise (collinearity.term_t_ratios), not the
    # residual's effective sample size; false: the effective sample size everywhere (before session 28)
    stated_noise_t: bool = True
    # nor is one whose terms the flight barely separates: a term with a VIF above max_vif on the fit rows,
    # unless its t ratio is at least min_t VIF / max_vif (vif_rule "scaled", identification.pareto
    # terms_identified; "cap": no VIF above max_vif, as before session 63)
    max_vif: float = 100.0
    vif_rule: str = "scaled"
    # nor is one whose self-feedback (d target / d own state, identification.self_feedback) is positive
    # beyond this many standard errors: anti-damping
    max_self_feedback_t: float = 1.0
    # a target is not excited by the flight when no candidate that passes these rules has a pick loss below
    # the constant model's by this fraction: it gets the minimal physical model (physics_candidates)
    min_gain: float = 0.05
    # with cv_folds 0: the chosen structure's coefficients refit on the fit and pick rows together
    # (identification.refit); false: they stay as fitted on the fit rows alone (cross-validation refits)
    refit_with_pick_rows: bool = False
    # > 1: the pick scores each candidate by blocked K-fold cross-validation over the fit and pick rows
    # (identification.cross_validation) instead of its loss on the pick rows, polishes the pick by one-term
    # moves scored alike (identification.cv_polish) and refits the chosen structure on both; 0: the pick
    # rows alone (as before session 15; docs/discovery-log.md "Where discovery stands (session 15)")
    cv_folds: int = 5
    # with cv_folds > 1, the t ratio and VIF rules (min_t, max_vif) are measured on the fit and pick rows,
    # those the chosen structure's coefficients are refit on (identification.cross_validation), not on the
    # fit rows alone: a term is identified by the rows that fit it. Realistic-sensor fang-chen-aero (seed 5,
    # weak form): fz's wz^2 has t 1.6-3.1 on the fit rows, where the yaw rate barely varies (its spread 3.7
    # against 28.5 on the pick rows), and 17-19 on both; false: the fit rows alone (before session 38)
    identify_on_pick_rows: bool = True
    # the rows are cut into cv_folds x this many contiguous blocks, dealt to the folds in turn: a fold's
    # held-out rows spread over the flight (one block per fold makes each fold's fit extrapolate to a
    # regime it never saw, such as the fast fall of an open-loop flight)
    cv_blocks_per_fold: int = 6
    # the cross-validated polish (identification.cv_polish) takes no one-term move whose held-out
    # predictions are worse than the pick's by more than this many paired standard errors (paired_loss_t
    # over the folds' blocks), though within the pick's tolerance: a term the flight pins down is not
    # dropped for being small (closed-loop fang-chen-aero's fz: wx*wz, 5 % of the cross-validated loss at
    # t 4, under the tolerance's absolute part). 0: off (the tolerance alone, as before session 21)
    cv_polish_z: float = 2.0
    # the cross-validated polish may also swap in, for each term of the pick, this many features of the
    # engine's space most correlated with it on the fit rows (its shape twins: |wz| beside wz^2, which no
    # candidate may hold); 0: only the candidates' terms
    cv_polish_twins: int = 3
    # and this many features of the engine's space most correlated with the pick's cross-validated residual
    # over the fit and pick rows: the engine screens on the fit rows alone, so a term only the pick rows
    # excite (a flight that yaws late: the yaw couplings) is in none of its candidates; 0: none
    cv_polish_residual: int = 5
    # and each height term of the pick that reads no rotor speed, times the rotors' thrust sum
    # u1^2 + .. + u4^2 (cv_polish.thrust_twins): a ground effect scales the thrust, and near hover the bare
    # law fits nearly as well, so the screening takes it (closed-loop realistic-sensor fang-chen-aero, seed
    # 19: fz held -0.008/h^2 and its constant, the accelerometer's bias, 42 % off); false: none
    cv_polish_thrust_twins: bool = True
    # the cross-validated polish also moves on from this many models per round that are better than the pick
    # and no larger yet not picked (tied terms: unidentified), lowest loss first: the way to a better model
    # the rule can pick may pass through such models, which a polish of the pick alone never reaches.
    # Realistic-sensor fang-chen-aero (seed 23) fy: sum(u) stood for the constant and wx + wx sum(u^2) for
    # wx sum(u), and every model between the pick and the true one was unidentified. 0: the pick's moves
    # alone (before session 51; bench/settings/polish-pick-alone.yaml)
    cv_polish_beam: int = 2
    # the polish stops when its pick stays and no such model is left to move on from, or after this many
    # rounds (4 before session 51, when each round moved from the pick alone)
    cv_polish_rounds: int = 8
    # where the polished pick holds a hub law (a ground effect), its own coefficients are refit beside the
    # pick's other terms (identification.law_refit) and the polish moves on from there, at most this many
    # times, until the pick stays: the law was fitted beside the terms of an earlier model, and its stale
    # residual hid small terms the flight pins down (seed 41's heavy closed loop: wx^2 in wx' at t 6 -> 13).
    # 0: off (before session 65)
    cv_polish_law_refits: int = 2
    # the chosen structure's refit (on the fit and pick rows) by generalised least squares where the rows
    # are weak and the log states its targets' raw noise (identification.weak_noise): the weak rows' noise
    # covariance weighs them, which the gyro's differences need for small terms (a closed-loop flight's rate
    # dampings); false: ordinary least squares on the weak rows, as the candidates were fitted
    refit_gls: bool = True
    # of the candidates within the pick's tolerance, at most one term larger than the pick, whose structure
    # Hausman's test on the fit and pick rows does not reject and whose terms the rule passes (each term's t
    # ratio the better of the weak rows' own fit and the generalised one), the fewest terms and then the
    # simplest the rows support as well as any, when it rejects the pick's
    # (identification.specification_pick; weak rows with a stated noise only)
    specification_pick: bool = True
    # when no such candidate passes: at most this many steps of the specification search, each adding a
    # term of any candidate's (or the polish's extra ones, or a factor of one) or putting one in another's
    # place, to the structure whose generalised fit leaves the least residual; what it finds must pass the
    # test, the pick's rule and tolerance
    # (identification.specification_search; 0: no search)
    specification_search: int = 3
    # that refit's standard errors go in the model file; a term whose standard error is above this fraction
    # of its coefficient is named on the terminal as not pinned down by the flight
    report_relative_se: float = 0.1
    # up to this many terms whose addition to the chosen structure lowers the cross-validated loss by at
    # least min_t paired standard errors over the folds' blocks, within the pick's tolerance, are named in
    # the model file and on the terminal, not added (identification.supported_terms; cv_folds > 1); 0: none
    report_supported: int = 3


@dataclass(frozen=True)
class EngineSettings:
    """All engine settings."""

    sparse: SparseSettings = SparseSettings()
    operon: OperonSettings = OperonSettings()
    pysr: PysrSettings = PysrSettings()
    selection: SelectionSettings = SelectionSettings()
    discovery: DiscoverySettings = DiscoverySettings()

    def as_dict(self) -> dict[str, Any]:
        """Plain mapping (for the model file)."""
        return _plain(dataclasses.asdict(self))


def _plain(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def load_engine_settings(path: str | os.PathLike[str] | None) -> EngineSettings:
    """Engine settings from a YAML file (None: the defaults); a bad key or value is a UserError."""
    if path is None:
        return EngineSettings()
    where = f"settings file {path}"
    p = Path(path)
    if not p.is_file():
        raise UserError(f"{where}: not found", hint="give the path of an engine settings YAML file")
    data = load_yaml_file(p, where)
    settings = read_dataclass(Section(where, data or {}, hint=SETTINGS_HINT), EngineSettings)
    folds = settings.selection.cv_folds
    if folds == 1 or folds < 0:
        raise UserError(f"{where}: key 'selection.cv_folds': {folds} folds",
                        hint="0 (pick on the pick rows alone) or 2 or more (blocked K-fold cross-validation)")
    if settings.selection.cv_blocks_per_fold < 1:
        raise UserError(f"{where}: key 'selection.cv_blocks_per_fold': must be 1 or more",
                        hint="the blocks each fold holds out, spread over the flight")
    if settings.selection.cv_polish_rounds < 0:
        raise UserError(f"{where}: key 'selection.cv_polish_rounds': must be 0 or more",
                        hint="the most rounds of moves the polish makes, e.g. 8")
    if settings.selection.cv_polish_law_refits < 0:
        raise UserError(f"{where}: key 'selection.cv_polish_law_refits': must be 0 or more",
                        hint="the most times the pick's ground-effect law is refit and polished from, e.g. 2")
    if settings.selection.cv_polish_beam < 0:
        raise UserError(f"{where}: key 'selection.cv_polish_beam': must be 0 or more",
                        hint="the models beside the pick the polish moves on from per round, e.g. 2")
    if settings.selection.vif_rule not in VIF_RULES:
        raise UserError(f"{where}: key 'selection.vif_rule': unknown rule {settings.selection.vif_rule!r}",
                        hint=f"known: {', '.join(VIF_RULES)}")
    if not settings.selection.report_relative_se > 0:
        raise UserError(f"{where}: key 'selection.report_relative_se': must be above 0",
                        hint="the fraction of a coefficient its standard error may reach unnamed, e.g. 0.1")
    if settings.selection.report_supported < 0:
        raise UserError(f"{where}: key 'selection.report_supported': must be 0 or more",
                        hint="the most terms the flight supports beyond the pick to name, e.g. 3 (0: none)")
    bad = [g for g in settings.sparse.groups if g not in GROUPS]
    if bad:
        raise UserError(
            f"{where}: key 'sparse.groups': unknown group {bad[0]!r}", hint=f"known: {', '.join(GROUPS)}"
        )
    return settings
