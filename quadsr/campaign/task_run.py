"""One campaign task, run inside a Dask worker: its own vehicle file, its own SITL child, one flight.

A task's vehicle is the nominal vehicle file with the task's vehicle-key values written in; the SITL flies
that vehicle (with the task's seed, sensor preset and wind), while the controller is built for the nominal
vehicle and model, as an engineer's controller would be. Nothing here depends on the client's file system:
the nominal vehicle and the models travel as text in the TaskContext. A task never raises for a flight that
went wrong: crashes and failures are rows with their reason.
"""

from __future__ import annotations

import hashlib
import math
import shutil
import tempfile
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from bridge.errors import UserError
from bridge.yaml_file import load_yaml_text
from quadsr.campaign.tasks import Task

# Metrics copied into a result row, from controller.metrics.FlightMetrics (SI: m, s, rad).
METRIC_FIELDS = ("rms_m", "rms_after_5s_m", "max_m", "final_m", "settle_time_s", "yaw_rms_rad",
                 "yaw_max_rad", "motor_limit_share", "max_tilt_deg")
# Columns that depend on the machine (not part of the deterministic results table).
TIMING_FIELDS = ("wall_s", "step_median_us", "step_p99_us")
PATIENT = ("--lockstep-timeout", "30")  # a loaded worker must not send its SITL into failsafe


@dataclass(frozen=True)
class TaskContext:
    """What every task of a campaign shares: the nominal vehicle file's text and the models' texts."""

    vehicle_name: str
    vehicle_yaml: str  # the nominal vehicle file, as text
    true_model_yaml: str  # the nominal vehicle's exact model (quadsr model-from-vehicle), as text
    learned_model_yaml: str | None  # the model learned once on the nominal vehicle (pipeline fly), as text
    pipeline: str = "fly"
    identify_budget: int = 60  # genetic-programming generations per target (learn-fly)
    keep_flights: str | None = None  # a folder to copy each task's flight folder into (shared file system)
    trajectory_files: dict[str, str] | None = None  # trajectory value -> file text (not built-in ones)


def task_vehicle_yaml(nominal_yaml: str, params: dict[str, Any], vehicle_keys: tuple[str, ...]) -> str:
    """The nominal vehicle file's text with the task's vehicle-key values written in."""
    data = load_yaml_text(nominal_yaml, "the nominal vehicle file")
    for key in vehicle_keys:
        node = data
        parts = key.split(".")
        for part in parts[:-1]:
            node = node[part]
        value = params[key]
        node[parts[-1]] = list(value) if isinstance(value, tuple) else value
    return yaml.safe_dump(data, sort_keys=False)


def wind_args(params: dict[str, Any], seed: int) -> list[str]:
    """The SITL's wind flags for a task (none without wind): --wind=N,E,D [--turbulence P --wind-seed S]."""
    speed = float(params.get("wind_speed", 0.0))
    down = float(params.get("wind_down", 0.0))
    turbulence = params.get("turbulence", "none")
    if speed == 0.0 and down == 0.0 and turbulence == "none":
        return []
    direction = float(params.get("wind_direction", 0.0))
    north, east = speed * math.cos(direction), speed * math.sin(direction)
    args = [f"--wind={north:.6g},{east:.6g},{down:.6g}"]  # '=': a negative north must not read as a flag
    if turbulence != "none":
        args += ["--turbulence", str(turbulence), "--wind-seed", str(seed)]
    return args


_CONTROLLERS: dict[tuple[str, str, str], Any] = {}  # per worker process: built controllers, reset per flight


def _controller(name: str, model_yaml: str | None, vehicle_path: Path, vehicle_text: str, work: Path) -> Any:
    """The controller for the nominal vehicle (and model), built once per worker process and reused."""
    from bridge.vehicle import load_vehicle
    from controller.registry import make_controller

    digest = hashlib.sha256((model_yaml or "").encode()).hexdigest()
    key = (name, digest, hashlib.sha256(vehicle_text.encode()).hexdigest())
    if key not in _CONTROLLERS:
        model_path = None
        if model_yaml is not None:
            model_path = work / f"model-{digest[:12]}.yaml"
            model_path.write_text(model_yaml)
        _CONTROLLERS[key] = make_controller(name, model_path, load_vehicle(vehicle_path))
    controller = _CONTROLLERS[key]
    controller.reset()
    return controller


def _learn(task: Task, ctx: TaskContext, vehicle_path: Path, work: Path,
           sitl_args: list[str]) -> tuple[str, dict]:
    """learn-fly: excite the task's vehicle, identify, validate on a second flight; model text, row."""
    from identification.dataset import load_dataset
    from identification.identify import identify
    from identification.model_file import load_model, save_model
    from identification.validate import evaluate_model
    from quadsr.pipeline import fly_excitation

    open_loop = task.params["profile"].startswith("paper")
    args = ["--vehicle", str(vehicle_path), "--sensors", task.params["sensors"], "--seed", str(task.seed),
            *(("--ground", "none", "--initial-position", "0,0,-200") if open_loop else ()), *PATIENT,
            *sitl_args]
    duration = float(task.params["learn_duration"])
    train, check = work / "train.tlog", work / "validate.tlog"
    fly_excitation(task.params["profile"], train, sitl_args=args, seed=task.seed, duration=duration,
                   vehicle=str(vehicle_path))
    fly_excitation(task.params["profile"], check, sitl_args=args, seed=task.seed + 1, duration=duration,
                   vehicle=str(vehicle_path))
    targets_from = "sensors" if task.params["sensors"] == "realistic" else "truth"
    model = identify(load_dataset(train, targets=targets_from), engine="default",
                     budget=ctx.identify_budget, seed=task.seed, progress=False)
    path = save_model(model, work / "learned.yaml")
    _, metrics = evaluate_model(load_model(path), load_dataset(check, targets=targets_from))
    row = {f"r2_{target}": float(m["r2"]) for target, m in metrics.items()}
    return path.read_text(), row


def run_task(task: Task, ctx: TaskContext, vehicle_keys: tuple[str, ...]) -> dict[str, Any]:
    """Fly one task; its result row (parameters, status, reason, metrics, timings). Never raises."""
    from quadsr.sitl_process import SitlProcess

    start = time.perf_counter()
    row: dict[str, Any] = {"task_id": task.task_id, "seed": task.seed, **task.params,
                           "status": "failed", "reason": ""}
    work = Path(tempfile.mkdtemp(prefix=f"quadsr-task-{task.task_id}-"))
    try:
        from bridge.vehicle import load_vehicle
        from controller.companion import Companion, FlightSettings
        from controller.trajectories import load_trajectory

        nominal_path = work / f"{ctx.vehicle_name}.yaml"
        nominal_path.write_text(ctx.vehicle_yaml)
        vehicle_path = work / f"{ctx.vehicle_name}-task.yaml"
        vehicle_path.write_text(task_vehicle_yaml(ctx.vehicle_yaml, task.params, vehicle_keys))
        load_vehicle(vehicle_path)  # a drawn value the vehicle file refuses is this task's failure
        extra = wind_args(task.params, task.seed)
        name = task.params["controller"]
        model_yaml = None
        if name == "backstepping-true":
            model_yaml = ctx.true_model_yaml
        elif name == "backstepping-learned":
            if ctx.pipeline == "learn-fly":
                model_yaml, learned = _learn(task, ctx, vehicle_path, work, extra)
                row.update(learned)
            else:
                model_yaml = ctx.learned_model_yaml
        kind = name.split("-")[0]
        controller = _controller(kind, model_yaml, nominal_path, ctx.vehicle_yaml, work)
        trajectory_ref = task.params["trajectory"]
        if ctx.trajectory_files and trajectory_ref in ctx.trajectory_files:
            trajectory_ref = work / "trajectory.yaml"
            trajectory_ref.write_text(ctx.trajectory_files[task.params["trajectory"]])
        trajectory = load_trajectory(trajectory_ref)
        args = ["--vehicle", str(vehicle_path), "--sensors", task.params["sensors"], "--seed", str(task.seed),
                *PATIENT, *extra]
        sitl = SitlProcess(args, log_path=work / "sitl.log")
        with sitl:
            settings = FlightSettings(hil=sitl.hil, duration=float(task.params["duration"]),
                                      state=task.params["state"], progress=False, link_timeout=30.0,
                                      figures=False)
            companion = Companion(controller, trajectory, load_vehicle(nominal_path), settings)
            result = companion.fly(work / "flight")
        metrics = result.metrics
        for f in METRIC_FIELDS:
            value = getattr(metrics, f, None) if metrics is not None else None
            row[f] = float(value) if value is not None else math.nan
        row["crashed"] = bool(result.crashed)
        row["completed"] = bool(result.completed)
        if result.completed:
            row["status"] = "ok"
        elif result.crashed:
            row["status"], row["reason"] = "crashed", result.message
        else:
            row["reason"] = result.message or "the flight did not run to its end"
        row["step_median_us"] = float(metrics.step_median_us) if metrics is not None else math.nan
        row["step_p99_us"] = float(metrics.step_p99_us) if metrics is not None else math.nan
        if ctx.keep_flights:
            shutil.copytree(work / "flight", Path(ctx.keep_flights) / task.task_id, dirs_exist_ok=True)
    except UserError as exc:
        row["reason"] = str(exc)
    except Exception as exc:  # a task's bug or crash must become its row, never a lost task
        row["reason"] = f"{type(exc).__name__}: {exc} | " + traceback.format_exc(limit=3).replace("\n", " ")
    finally:
        shutil.rmtree(work, ignore_errors=True)
    row["wall_s"] = time.perf_counter() - start
    return row
