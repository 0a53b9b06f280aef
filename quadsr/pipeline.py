"""`quadsr paper`: the paper end to end, stage by stage, each flight against its own `quadsr sitl` child.

Stages: true-model (the vehicle's exact equations, as `quadsr model-from-vehicle`), fly-train and
fly-validate (the paper's excitations, open loop from 200 m up with no ground and ideal sensors), identify
(default engine), validate (Table I, Fig. 3, term comparison against the true model), track (Case I and II
with backstepping on the learned and on the true model, the PID cascade and SE(3), each from the ground),
figures (Figs. 4-6).
report.md is rewritten after every stage, so a failed or interrupted run leaves what it had done readable.

The flight helpers (fly_excitation, fly_tracking) are shared with bench/identify_paper.py and
bench/track_paper.py.
"""

from __future__ import annotations

import datetime as _dt
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bridge.errors import UserError
from bridge.shutdown import StopSignals
from bridge.vehicle import load_vehicle
from quadsr.paper_run import (  # noqa: F401 - the run's records, also importable from here
    CASES,
    CONTROLLER_KEYS,
    LEARNED_LABEL,
    TRUE_LABEL,
    PaperRun,
    PaperSettings,
    StageRecord,
    TrackingRow,
)
from quadsr.sitl_process import SitlProcess

# SITL flags. A long lockstep wait bound: a busy machine must not send the SITL into failsafe mid-flight.
PATIENT_SITL: tuple[str, ...] = ("--lockstep-timeout", "30")
OPEN_LOOP_SITL: tuple[str, ...] = ("--ground", "none", "--initial-position", "0,0,-200", *PATIENT_SITL)
GROUND_SITL: tuple[str, ...] = PATIENT_SITL
SITL_START_TIMEOUT = 60.0  # s of wall time for a child to say it listens (20 s was exceeded at load 15)

DEFAULT_SETTINGS = PaperSettings("default", train_duration=32.0, budget=60, track_duration=20.0)
QUICK_SETTINGS = PaperSettings("quick", train_duration=16.0, budget=10, track_duration=12.0)


# --------------------------------------------------------------------------------------------------------
# SITL children and the shared flights


class SitlChildren:
    """Every `quadsr sitl` child of a run: started per flight, stopped after it, all stopped by stop_all()."""

    def __init__(self) -> None:
        self.started: list[SitlProcess] = []
        self.deaths: list[str] = []  # children that exited on their own while a flight was using them

    @contextmanager
    def child(self, args: Sequence[str], log_path: Path | None = None) -> Iterator[SitlProcess]:
        """Start a SITL child with these flags (free HIL port, no GCS), yield it, stop it afterwards."""
        sitl = SitlProcess(list(args), log_path=log_path)
        self.started.append(sitl)
        try:
            sitl.start(timeout=SITL_START_TIMEOUT)
            yield sitl
        finally:
            code = sitl.proc.poll() if sitl.proc is not None else None
            if code is not None:
                self.deaths.append(f"the SITL child (pid {sitl.proc.pid}) had exited with code {code} before "
                                   "the pipeline stopped it"
                                   + (f"; its log: {log_path}" if log_path else ""))
            sitl.stop()

    def stop_all(self) -> None:
        """Stop every child still running."""
        for sitl in self.started:
            sitl.stop()


def _child(children: SitlChildren | None, args: Sequence[str], log_path: Path | None):
    return (children or SitlChildren()).child(args, log_path)


def fly_excitation(profile: str, tlog: Path, *, sitl_args: Sequence[str], seed: int = 0,
                   duration: float | None = None, vehicle: str = "fang-chen-buaa", step_timeout: float = 1.0,
                   progress: bool = False, log_path: Path | None = None,
                   children: SitlChildren | None = None) -> Any:
    """Start a SITL child, fly one excitation profile into `tlog`, stop the SITL; the FlightSummary.

    duration: s simulated (None: the profile's); step_timeout: s to wait for each SITL step.
    """
    from identification.excite import fly

    tlog.parent.mkdir(parents=True, exist_ok=True)
    with _child(children, sitl_args, log_path) as sitl:
        return fly(profile, tlog, hil=sitl.hil, duration=duration, seed=seed, vehicle=vehicle,
                   step_timeout=step_timeout, progress=progress)


@dataclass(frozen=True)
class ControllerSpec:
    """One controller of the tracking table: its label, registry name and model file (backstepping only)."""

    label: str
    controller: str  # backstepping | pid | se3
    model: Path | None = None


def controller_specs(learned: Path | None, true_model: Path,
                     wanted: Sequence[str] = CONTROLLER_KEYS) -> list[ControllerSpec]:
    """The controllers flown: backstepping on the learned model (if given) and on the true model, pid, se3."""
    specs = []
    if "learned" in wanted and learned is not None:
        specs.append(ControllerSpec(LEARNED_LABEL, "backstepping", learned))
    if "true" in wanted:
        specs.append(ControllerSpec(TRUE_LABEL, "backstepping", true_model))
    specs += [ControllerSpec(name, name) for name in ("pid", "se3") if name in wanted]
    return specs


def flight_dir_name(label: str, case: str, state: str) -> str:
    """The folder name of one tracking flight, e.g. backstepping_learned_case1_truth (a trajectory file: its
    stem, so a path never nests folders)."""
    return f"{label.replace(' ', '_').replace('(', '').replace(')', '')}_{Path(case).stem}_{state}"


def fly_tracking(spec: ControllerSpec, case: str, *, duration: float, out: Path,
                 vehicle: str = "fang-chen-buaa", sensors: str = "ideal", state: str = "truth",
                 sitl_args: Sequence[str] = GROUND_SITL, link_timeout: float = 30.0, attempts: int = 3,
                 progress: bool = False, children: SitlChildren | None = None,
                 built: dict[str, Any] | None = None) -> TrackingRow:
    """Start a SITL child, fly one case with one controller from the ground, stop the SITL; the row.

    A flight during which the SITL reported a problem (a failsafe STATUSTEXT) is flown again, up to
    `attempts` times. A controller that cannot be built from its model gives a row without metrics.
    `built`: controllers already built, by label (reused, reset by the companion before each flight; the
    backstepping law's derivation is the slow part of a short flight), and where new ones are kept.
    """
    from controller.companion import Companion, FlightSettings
    from controller.registry import make_controller
    from controller.trajectories import load_trajectory

    veh = load_vehicle(vehicle)
    flight_dir = out / flight_dir_name(spec.label, case, state)
    out.mkdir(parents=True, exist_ok=True)
    try:
        controller = built.get(spec.label) if built is not None else None
        if controller is None:
            controller = make_controller(spec.controller, spec.model, veh)
            if built is not None:
                built[spec.label] = controller
    except UserError as exc:
        return TrackingRow(spec.label, case, state, None, f"controller not built: {exc}", flight_dir)
    trajectory = load_trajectory(case)
    args = ["--vehicle", str(veh.source_path or vehicle), "--sensors", sensors, *sitl_args]
    start = time.perf_counter()
    for _attempt in range(attempts):
        with _child(children, args, flight_dir.with_suffix(".sitl.log")) as sitl:
            settings = FlightSettings(hil=sitl.hil, duration=duration, state=state, progress=progress,
                                      link_timeout=link_timeout)
            result = Companion(controller, trajectory, veh, settings).fly(flight_dir)
        if not result.sitl_messages:
            break
        print(f"  {spec.label} {case}: the SITL said {result.sitl_messages}; flying it again", flush=True)
    message = result.message or "; ".join(result.sitl_messages)
    describe = getattr(controller, "describe", None)
    return TrackingRow(spec.label, case, state, result.metrics, message, flight_dir, result.completed,
                       result.crashed, time.perf_counter() - start,
                       link_lost=not result.completed and not result.crashed,
                       law=describe() if describe is not None else "")


# --------------------------------------------------------------------------------------------------------
# The run


class StageFailed(Exception):
    """A stage raised: names the stage and says why."""

    def __init__(self, stage: str, message: str):
        super().__init__(f"stage '{stage}' failed: {message}")
        self.stage = stage
        self.message = message


class StageInterrupted(Exception):
    """Ctrl-C (or SIGTERM) during a stage."""

    def __init__(self, stage: str, signal_name: str):
        super().__init__(f"interrupted ({signal_name}) during stage '{stage}'")
        self.stage = stage
        self.signal_name = signal_name

    @property
    def exit_code(self) -> int:
        """130 for Ctrl-C (SIGINT), 143 for SIGTERM (128 + the signal number)."""
        return 143 if self.signal_name == "SIGTERM" else 130


STAGES: tuple[tuple[str, str], ...] = (
    ("true-model", "the vehicle's exact equations (quadsr model-from-vehicle) -> true-model.yaml"),
    ("fly-train", "paper-train excitation: random held rotor speeds, open loop from 200 m, no ground"),
    ("fly-validate", "paper-validate excitation: the paper's 10 s sinusoids, open loop from 200 m"),
    ("identify", "symbolic regression, default engine, on the training flight -> model.yaml"),
    ("validate", "Table I, Fig. 3 and the term comparison on the validation flight"),
    ("track", "Case I and II: backstepping on the learned and the true model, pid, se3"),
    ("figures", "Figs. 4-6: tracking of every controller, 3-D paths"),
)


class PaperPipeline:
    """Runs the stages in order against SITL children, rewriting report.md after each one."""

    def __init__(self, run: PaperRun, echo: Callable[[str], None] | None = None):
        self.run = run
        self.children = SitlChildren()
        self.echo = echo or (lambda line: print(line, flush=True))
        self._signal_name = "SIGINT"
        self._t0 = time.perf_counter()

    # ---- stages

    def _true_model(self) -> str:
        from identification.model_file import save_model
        from identification.true_model import true_model

        r = self.run
        r.truth = true_model(r.vehicle)
        r.files["true_model"] = save_model(r.truth, r.out / "true-model.yaml")
        return f"wrote {r.files['true_model']}"

    def _sitl_flags(self, base: Sequence[str]) -> list[str]:
        r = self.run
        return [*base, "--vehicle", r.vehicle_ref, "--sensors", "ideal", "--seed", str(r.seed)]

    def _fly(self, profile: str, duration: float | None) -> str:
        r = self.run
        flights = r.out / "flights"
        summary = fly_excitation(
            profile, flights / f"{profile}.tlog", sitl_args=self._sitl_flags(OPEN_LOOP_SITL), seed=r.seed,
            duration=duration, vehicle=r.vehicle_ref, step_timeout=r.settings.link_timeout,
            progress=r.progress, log_path=flights / f"sitl-{profile}.log", children=self.children)
        r.flights[profile] = summary
        r.files[f"tlog_{profile}"] = summary.out
        if summary.status_texts:
            raise RuntimeError(f"the SITL reported a problem during {profile}: {summary.status_texts}")
        return (f"{summary.steps} steps ({summary.sim_time:.1f} s simulated), max tilt "
                f"{summary.max_tilt_deg:.0f} deg, max body rate {summary.max_rate:.1f} rad/s")

    def _fly_train(self) -> str:
        return self._fly("paper-train", self.run.settings.train_duration)

    def _fly_validate(self) -> str:
        return self._fly("paper-validate", None)

    def _identify(self) -> str:
        from identification.dataset import load_dataset
        from identification.identify import identify
        from identification.model_file import save_model
        from identification.target_pool import default_jobs
        from identification.true_model import vehicle_provenance

        r = self.run
        train = load_dataset(r.files["tlog_paper-train"])
        r.rows["train"] = len(train)
        # fit and pick on paper-train (time blocks), validate on the other flight (never seen by either)
        val = load_dataset(r.files["tlog_paper-validate"])
        r.model = identify(train, engine="default", budget=r.settings.budget, seed=r.seed, validate=val,
                           vehicle=vehicle_provenance(r.vehicle), progress=r.progress,
                           gravity=r.vehicle.gravity, jobs=default_jobs())
        r.files["model"] = save_model(r.model, r.out / "model.yaml")
        return f"{len(train)} rows; wrote {r.files['model']}"

    def _validate(self) -> str:
        from identification.dataset import load_dataset
        from identification.validate import validate
        from quadsr.report import write_identification_csv

        r = self.run
        val = load_dataset(r.files["tlog_paper-validate"])
        r.rows["validate"] = len(val)
        r.validation = validate(r.model, val, r.out / "validation", reference=r.truth)
        r.files["fig3"] = r.validation.figure
        r.files["identification_csv"] = write_identification_csv(r.validation.metrics,
                                                                  r.out / "identification.csv")
        worst = min(m["r2"] for m in r.validation.metrics.values())
        same = sum(c.same_terms for c in r.validation.comparisons or [])
        return f"{len(val)} rows; lowest R^2 {worst:.6f}; {same} of 6 targets with the true model's terms"

    def _track(self) -> str:
        from quadsr.report import write_tracking_csv

        r = self.run
        specs = controller_specs(r.files["model"], r.files["true_model"])
        folder = r.out / "tracking"
        r.tracking = []
        for case in CASES:
            for spec in specs:
                row = fly_tracking(spec, case, duration=r.settings.track_duration, out=folder,
                                   vehicle=r.vehicle_ref, sitl_args=[*GROUND_SITL, "--seed", str(r.seed)],
                                   link_timeout=r.settings.link_timeout, progress=r.progress,
                                   children=self.children)
                r.tracking.append(row)
                r.files["tracking_csv"] = write_tracking_csv(r.tracking, r.out / "tracking.csv")
                self.echo(f"      {_flight_line(row)}")
                if row.link_lost:
                    raise RuntimeError(f"{spec.label} on {case}: {row.message}")
        return f"{len(r.tracking)} flights"

    def _figures(self) -> str:
        from quadsr.figures import paths3d_figure, tracking_overlay_figure

        r = self.run
        r.files["fig4"] = tracking_overlay_figure(r.tracking, "case1", r.out / "fig4_case1_tracking.png")
        r.files["fig5"] = paths3d_figure(r.tracking, r.out / "fig5_paths3d.png")
        r.files["fig6"] = tracking_overlay_figure(r.tracking, "case2", r.out / "fig6_case2_tracking.png")
        return "wrote fig4_case1_tracking.png, fig5_paths3d.png, fig6_case2_tracking.png"

    # ---- the runner

    def _write_report(self) -> None:
        from quadsr.report import write_report

        self.run.elapsed_s = time.perf_counter() - self._t0
        self.run.files["report"] = write_report(self.run)

    def execute(self) -> PaperRun:
        """Run every stage; raises StageFailed or StageInterrupted (after writing the partial report)."""
        r = self.run
        steps: dict[str, Callable[[], str]] = {
            "true-model": self._true_model, "fly-train": self._fly_train, "fly-validate": self._fly_validate,
            "identify": self._identify, "validate": self._validate, "track": self._track,
            "figures": self._figures,
        }
        # SIGTERM as SIGINT; a repeated signal while the report is written and children stop is absorbed.
        signals = StopSignals(raise_interrupt=True).__enter__()
        try:
            self._write_report()
            n = len(r.stages)
            for i, record in enumerate(r.stages, 1):
                self.echo(f"[{i}/{n}] {record.name}: {record.title}")
                record.status = "running"
                self.children.deaths.clear()
                start = time.perf_counter()
                try:
                    record.note = steps[record.name]()
                except KeyboardInterrupt:
                    if signals.requested:
                        self._signal_name = signals.name
                    record.status, record.wall_s = "interrupted", time.perf_counter() - start
                    r.failure = f"interrupted ({self._signal_name}) during stage '{record.name}'"
                    self.children.stop_all()
                    self._write_report()
                    raise StageInterrupted(record.name, self._signal_name) from None
                except Exception as exc:  # noqa: BLE001 - every failure is reported under its stage's name
                    record.status, record.wall_s = "failed", time.perf_counter() - start
                    message = _failure_text(exc, self.children.deaths)
                    record.note = message
                    r.failure = f"stage '{record.name}' failed: {message}"
                    self.children.stop_all()
                    self._write_report()
                    raise StageFailed(record.name, message) from exc
                record.status, record.wall_s = "done", time.perf_counter() - start
                self.echo(f"[{i}/{n}] {record.name}: done in {record.wall_s:.1f} s "
                          f"(total {time.perf_counter() - self._t0:.1f} s): {record.note}")
                self._write_report()
            r.finished = True
            self._write_report()
            return r
        finally:
            self.children.stop_all()
            signals.__exit__(None, None, None)


def _failure_text(exc: BaseException, deaths: Sequence[str]) -> str:
    """What went wrong, then which SITL children died, then the hint (for a UserError)."""
    text = (str(exc.args[0]) if exc.args else "").strip() or type(exc).__name__
    if not isinstance(exc, (UserError, RuntimeError)):
        text = f"{type(exc).__name__}: {text}"
    if deaths:
        text += " (" + "; ".join(deaths) + ")"
    hint = getattr(exc, "hint", None)
    return f"{text}\n  hint: {hint}" if hint else text


def _flight_line(row: TrackingRow) -> str:
    from quadsr.report import millimetres

    m = row.metrics
    if m is None:
        return f"{row.label} {row.case}: no data ({row.message})"
    after = f"{millimetres(m.rms_after_5s_m)} mm"
    state = "flown to the end" if row.completed else (row.message or "stopped early")
    return (f"{row.label} {row.case}: RMS after 5 s {after}, max {m.max_m:.2f} m, {state} "
            f"({row.wall_s:.1f} s)")


def prepare_run(out: Path, seed: int, quick: bool, vehicle: str, command: str,
                progress: bool | None = None) -> PaperRun:
    """Check the arguments (UserError when wrong) and make the output folder; the run, not yet started."""
    if seed < 0:
        raise UserError(f"--seed must be >= 0, got {seed}")
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out} exists and is not a directory", hint="give a folder for the results")
    veh = load_vehicle(vehicle)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"cannot create --out {out}: {exc.strerror}") from None
    return PaperRun(
        out=out, settings=QUICK_SETTINGS if quick else DEFAULT_SETTINGS, seed=seed, vehicle=veh,
        command=command, started_utc=_dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
        stages=[StageRecord(name, title) for name, title in STAGES],
        progress=sys.stderr.isatty() if progress is None else progress,
    )


def run_paper(run: PaperRun, echo: Callable[[str], None] | None = None) -> PaperRun:
    """Run the whole pipeline for a prepared run; raises StageFailed or StageInterrupted."""
    return PaperPipeline(run, echo).execute()

