"""The records of a `quadsr paper` run: its settings, stages, tracking flights and the run itself.

Apart from quadsr/pipeline.py (which fills them) so that report.py and figures.py, which read them, do not
import the pipeline (they would form an import cycle with it).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bridge.vehicle import VehicleConfig

CASES: tuple[str, ...] = ("case1", "case2")
CONTROLLER_KEYS: tuple[str, ...] = ("learned", "true", "pid", "se3")
LEARNED_LABEL = "backstepping (learned)"
TRUE_LABEL = "backstepping (true model)"


@dataclass(frozen=True)
class PaperSettings:
    """A run's budgets: flight lengths [s, simulated], SR generations per target, link timeout [s]."""

    name: str  # default | quick
    train_duration: float  # s, the paper-train flight (its four speed groups share it evenly)
    budget: int  # genetic-programming generations per target (an iteration budget, not seconds)
    track_duration: float  # s, each tracking flight
    link_timeout: float = 10.0  # s a client waits for the SITL's next step before it gives up

    def describe(self) -> str:
        """One line: the budgets."""
        per_group = int(round(self.train_duration / 4 / 0.004))
        return (f"{self.name} budgets: paper-train {self.train_duration:g} s ({per_group} samples per "
                f"speed group), SR budget {self.budget} generations per target, tracking flights "
                f"{self.track_duration:g} s")


@dataclass
class TrackingRow:
    """One tracking flight: controller, case, state source, its metrics (None: no data) and outcome."""

    label: str
    case: str
    state: str  # truth | sensors
    metrics: Any  # controller.metrics.FlightMetrics | None
    message: str  # why it stopped early or was not flown ('' when it ran to the end)
    flight_dir: Path | None = None
    completed: bool = False
    crashed: bool = False
    wall_s: float = 0.0
    link_lost: bool = False  # the SITL stopped answering: a failure of the run, not of the controller
    law: str = ""  # how the controller was built (its describe(): the derived law), '' if it says nothing


@dataclass
class StageRecord:
    """One stage of the run: its name, what it does, its status and wall time [s]."""

    name: str
    title: str
    status: str = "not run"  # not run | running | done | failed | interrupted
    wall_s: float | None = None
    note: str = ""


@dataclass
class PaperRun:
    """Everything one run did and produced, as far as it got (what report.md is written from)."""

    out: Path
    settings: PaperSettings
    seed: int
    vehicle: VehicleConfig
    command: str
    started_utc: str
    stages: list[StageRecord]
    progress: bool = False
    files: dict[str, Path] = field(default_factory=dict)  # key -> written file
    flights: dict[str, Any] = field(default_factory=dict)  # profile -> identification FlightSummary
    rows: dict[str, int] = field(default_factory=dict)  # dataset rows: train, validate
    model: Any = None  # identification.model_file.Model (learned)
    truth: Any = None  # the true Model
    validation: Any = None  # identification.validate.ValidationReport
    tracking: list[TrackingRow] = field(default_factory=list)
    failure: str | None = None  # "stage 'x' failed: ..." or "interrupted ..."
    finished: bool = False
    elapsed_s: float = 0.0  # s wall since the pipeline started (stages, report writing, SITL start-ups)

    @property
    def vehicle_ref(self) -> str:
        """The vehicle file's path (or its name) as the SITL and the clients take it."""
        return str(self.vehicle.source_path or self.vehicle.name)

    @property
    def total_wall_s(self) -> float:
        """Sum of the stages' wall times [s]."""
        return sum(s.wall_s or 0.0 for s in self.stages)

    def stage(self, name: str) -> StageRecord:
        """The record of stage `name`."""
        return next(s for s in self.stages if s.name == name)
