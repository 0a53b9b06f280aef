"""From a dataset to a model: per target run the engine, build the Pareto front, pick on held-out data.

Held-out data: the last `holdout` fraction of each flight (in time). Losses: 'absolute' (MAE, the paper's
fitness) or 'squared' (RMSE), in the target's unit. The pick rule is identification.pareto's.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from bridge.errors import UserError
from identification.body_frame import (
    BODY_TARGET_NAMES,
    STANDARD_GRAVITY,
    body_fit_names,
    body_targets,
    composed_targets,
    primitive_info,
)
from identification.engine import ENGINE_NAMES, EngineSettings, make_engine
from identification.metrics import LOSSES, table_metrics
from identification.model_file import TARGET_NAMES, BodyModel, Model, TargetModel
from identification.pareto import attach_holdout, front_points, select


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


def identify(
    dataset: Any,
    *,
    engine: str = "default",
    targets: Sequence[str] = TARGET_NAMES,
    budget_s: float = 60.0,
    seed: int = 0,
    holdout: float = 0.2,
    loss: str = "absolute",
    settings: EngineSettings | None = None,
    vehicle: dict[str, Any] | None = None,
    progress: bool = True,
    log: Callable[[str], None] | None = None,
    gravity: float = STANDARD_GRAVITY,
) -> Model:
    """Identify the targets from a Dataset (identification.dataset); returns a learned Model.

    An engine that learns in the body frame (frame "body", the default engine) fits fx fy fz dwx dwy dwz
    (identification.body_frame, with `gravity` in m/s^2) and the NED targets are composed from them.
    """
    if engine not in ENGINE_NAMES:
        raise UserError(f"unknown engine {engine!r}", hint=f"choose one of {', '.join(ENGINE_NAMES)}")
    if loss not in LOSSES:
        raise UserError(f"unknown loss {loss!r}", hint=f"choose one of {', '.join(LOSSES)}")
    if not budget_s > 0:
        raise UserError(f"the budget must be a positive number of seconds per target, got {budget_s}")
    if seed < 0:
        raise UserError(f"the seed must be >= 0, got {seed}")
    settings = settings or EngineSettings()
    train, hold = dataset.split(holdout)
    if len(train) < 20:
        raise UserError(
            f"{dataset.source}: only {len(train)} training rows after holding out {holdout:.0%}",
            hint="fly longer, or give more logs",
        )
    X = np.hstack([train.xi, train.u])
    Xh = np.hstack([hold.xi, hold.u])
    body_frame = getattr(make_engine(engine, settings), "frame", "ned") == "body"
    fit_names, Y, Yh = tuple(targets), train.targets, hold.targets
    if body_frame:
        fit_names = body_fit_names(targets)
        Y, Yh = body_targets(train.xi, Y, gravity), body_targets(hold.xi, Yh, gravity)
    targets_done: dict[str, TargetModel] = {}
    wall: dict[str, dict[str, float]] = {}
    gates: dict[str, float] = {}
    notes: list[str] = []
    total_start = time.perf_counter()
    for name in fit_names:
        j = (BODY_TARGET_NAMES if body_frame else TARGET_NAMES).index(name)
        y, yh = Y[:, j], Yh[:, j]
        ok = np.all(np.isfinite(X), axis=1) & np.isfinite(y)
        okh = np.all(np.isfinite(Xh), axis=1) & np.isfinite(yh)
        eng = make_engine(engine, settings)
        bar = _Bar(name, progress)
        start = time.perf_counter()
        try:
            candidates = eng.fit(X[ok], y[ok], name, budget_s, seed, loss, bar, (Xh[okh], yh[okh]))
        except BaseException:
            bar.close("failed")
            raise
        if not candidates:
            bar.close("no candidates")
            raise UserError(f"engine {engine} found no expression for {name}", hint="raise --budget")
        attach_holdout(candidates, Xh[okh], yh[okh], loss)
        chosen = select(candidates, settings.selection, scale=float(np.std(yh[okh])) if okh.any() else 1.0)
        elapsed = time.perf_counter() - start
        metrics = {"train": table_metrics(y[ok], chosen.evaluate(X[ok]))}
        if okh.any():
            metrics["validation"] = table_metrics(yh[okh], chosen.evaluate(Xh[okh]))
        timings = {k: round(v, 3) for k, v in getattr(eng, "timings", {}).items()}
        timings["total"] = round(elapsed, 3)
        wall[name] = timings
        if getattr(eng, "gate_r2", None) is not None:
            gates[name] = float(eng.gate_r2)
        if getattr(eng, "capped_by_time", False):
            notes.append(
                f"{name}: genetic programming stopped at the time budget before its generation budget "
                "(the result may differ on a faster or slower machine; raise --budget)"
            )
        targets_done[name] = TargetModel(
            name=name,
            expression=chosen.expression,
            pareto=front_points(candidates, chosen),
            metrics=metrics,
            engine=chosen.engine,
            wall_time_s=elapsed,
        )
        r2v = metrics.get("validation", metrics["train"])["r2"]
        bar.close(f"R2={r2v:.6f} complexity {chosen.complexity} ({chosen.engine})")
        if log:
            log(f"{name}: R2 {r2v:.6f}, complexity {chosen.complexity}, {chosen.engine}, {elapsed:.1f} s")
    body = None
    if body_frame:
        body = BodyModel(targets_done, primitive_info(), gravity)
        targets_done = composed_targets(body, targets, X, train.targets, Xh, hold.targets)
    flights = [
        {
            "file": f.file,
            "sha256": f.sha256,
            "format": f.format,
            "rows": f.rows,
            "targets_from": f.target_source,
        }
        for f in dataset.flights
    ]
    engine_info: dict[str, Any] = {
        "name": engine,
        "loss": loss,
        "seed": seed,
        "budget_s_per_target": budget_s,
        "holdout_fraction": holdout,
        "selection": "smallest complexity with held-out loss <= best*(1+rel_tol) + abs_tol*std(held-out y)",
        "settings": settings.as_dict(),
        "wall_time_s": wall,
        "total_wall_time_s": round(time.perf_counter() - total_start, 3),
        "rows": {"train": int(len(train)), "holdout": int(len(hold)), "dropped": int(dataset.dropped_rows)},
    }
    if gates:
        engine_info["sparse_holdout_r2"] = gates
    if notes:
        engine_info["notes"] = notes
        for note in notes:
            print(f"note: {note}", file=sys.stderr)
    if body_frame:
        engine_info["learned_in"] = "body frame FRD: fx fy fz dwx dwy dwz; ax ay az = R f_b + g e_z"
    return Model(
        targets_done, kind="learned", vehicle=vehicle, flights=flights, engine=engine_info, body=body
    )
