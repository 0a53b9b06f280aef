"""The offboard companion's flight loop: SITL observation -> state -> controller -> throttles, per 4 ms step.

Per step: the state fed back is the SITL's truth (HIL_STATE_QUATERNION + LOCAL_POSITION_NED) or the
estimate from HIL_SENSOR/HIL_GPS (controller.estimator); the controller's motor speeds [rad/s] become
throttles through the vehicle's motor curve and answer the step's HIL_SENSOR. Everything crossing the link is
in DIR/flight.tlog; every step is a row of DIR/steps.csv (flushed each simulated second). At the end (or when
the link is lost) DIR gets metrics.md, metrics.csv, tracking.png and path3d.png.

The reference flown is the trajectory shaped by controller.reference_shaping (for every controller): a
take-off phase when it starts in the air, a time-scaling governor when it is beyond the vehicle's limits
(`FlightSettings.takeoff` / `.governor`; None turns one off). It is built at the first step from the
fed-back position, and the figures and metrics compare the vehicle with it.

Lost link: if no sensor message arrives for `link_timeout` (0.5 s) the companion stops commanding and the
flight ends with completed = False and a message saying so (the CLI exits non-zero).
"""

from __future__ import annotations

import csv
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bridge.errors import UserError
from bridge.lockstep import LinkLost, LockstepClient
from bridge.messages import Observation
from bridge.tlog import TlogWriter
from bridge.vehicle import EXCHANGE_STEP, VehicleConfig
from controller.estimator import EstimatorSettings, StateEstimator
from controller.metrics import FlightMetrics, compute_metrics, write_metrics
from controller.plugin import Controller, Reference, Trajectory, VehicleState
from controller.reference_shaping import GovernorSettings, TakeoffSettings, shaped_reference

STATE_SOURCES = ("truth", "sensors")
DEFAULT_HIL = "udp:127.0.0.1:4560"
AIRBORNE_HEIGHT = 0.3  # m above ground: from then on, touching the ground again counts as a crash
CRASH_TILT = math.radians(80.0)  # rad
FLUSH_EVERY = 250  # steps (1 s simulated)

CSV_COLUMNS = (
    ["t", "ref_x", "ref_y", "ref_z", "ref_vx", "ref_vy", "ref_vz", "ref_yaw"]
    + ["x", "y", "z", "vx", "vy", "vz", "phi", "theta", "psi", "wx", "wy", "wz"]
    + ["true_x", "true_y", "true_z", "true_vx", "true_vy", "true_vz", "true_phi", "true_theta", "true_psi"]
    + ["w1", "w2", "w3", "w4", "cmd_w1", "cmd_w2", "cmd_w3", "cmd_w4"]
    + ["throttle1", "throttle2", "throttle3", "throttle4", "saturated", "control_us", "loop_us"]
)


@dataclass(frozen=True)
class FlightSettings:
    """How to fly: HIL address, length [s], state source, link timeouts [s], progress bar."""

    hil: str = DEFAULT_HIL
    duration: float = 20.0
    state: str = "truth"  # truth | sensors
    link_timeout: float = 0.5  # s without a sensor message before the companion gives up
    connect_timeout: float = 10.0  # s to wait for the SITL's first step
    progress: bool = True
    figures: bool = True  # write tracking.png and path3d.png at the end (campaigns switch them off)
    estimator: EstimatorSettings = field(default_factory=EstimatorSettings)
    # reference shaping (controller.reference_shaping), for every controller: None turns a part off
    takeoff: TakeoffSettings | None = field(default_factory=TakeoffSettings)
    governor: GovernorSettings | None = field(default_factory=GovernorSettings)


@dataclass
class FlightResult:
    """What a flight produced: its metrics, whether it ran to the end, and why not."""

    metrics: FlightMetrics | None
    completed: bool
    crashed: bool
    message: str  # why the flight stopped early ('' when it ran to the end)
    steps: int
    out_dir: Path
    files: dict[str, Path]
    link_stats: dict[str, Any]
    sitl_messages: list[str] = field(default_factory=list)  # STATUSTEXTs from the SITL (e.g. a failsafe)


class StepLog:
    """Per-step rows: kept in memory for metrics and plots, and streamed to a CSV flushed every second."""

    def __init__(self, path: Path):
        self.path = path
        self._fh = path.open("w", newline="", encoding="utf-8")
        self._writer = csv.writer(self._fh)
        self._writer.writerow(CSV_COLUMNS)
        self.rows: list[list[float]] = []

    def add(self, row: list[float]) -> None:
        """Append one step's row (CSV_COLUMNS order)."""
        self.rows.append(row)
        self._writer.writerow([f"{v:.9g}" for v in row])
        if len(self.rows) % FLUSH_EVERY == 0:
            self._fh.flush()

    def close(self) -> None:
        """Flush and close the CSV."""
        if not self._fh.closed:
            self._fh.flush()
            self._fh.close()

    def array(self) -> np.ndarray:
        """The rows as an (N, len(CSV_COLUMNS)) array."""
        return np.array(self.rows, dtype=float).reshape(-1, len(CSV_COLUMNS))


def _col(name: str) -> int:
    return CSV_COLUMNS.index(name)


def _tilt(phi: float, theta: float) -> float:
    return math.acos(max(-1.0, min(1.0, math.cos(phi) * math.cos(theta))))


def flight_label(controller: Controller) -> str:
    """The controller's name with the model it flies on, e.g. 'backstepping on true-model true-model.yaml'."""
    model = getattr(controller, "model_label", "")
    return f"{controller.name} ({model})" if model else f"{controller.name} (no model)"


def open_flight_outputs(out_dir: str | Path) -> tuple[Path, dict[str, Path], TlogWriter, StepLog]:
    """A flight's folder (made if missing), its files {tlog, steps} and their open writers (tlog, CSV)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = {"tlog": out / "flight.tlog", "steps": out / "steps.csv"}
    return out, files, TlogWriter(files["tlog"]), StepLog(files["steps"])


class Companion:
    """One flight of a controller along a trajectory against a SITL over its HIL link (see module doc)."""

    def __init__(self, controller: Controller, trajectory: Trajectory, vehicle: VehicleConfig,
                 settings: FlightSettings | None = None):
        self.controller = controller
        self.trajectory = trajectory
        self.vehicle = vehicle
        self.settings = settings or FlightSettings()
        self.curve = vehicle.motor_curve
        sensors = self.settings.state == "sensors"
        self.estimator = StateEstimator(vehicle, self.settings.estimator) if sensors else None
        self._last_speeds = np.zeros(4)
        self._last_state: VehicleState | None = None
        self.flown: Any = None  # the reference as flown (take-off phase, governor), set at the first step

    def feedback(self, obs: Observation) -> VehicleState:
        """The state fed back to the controller for this observation (truth or estimate)."""
        speeds = obs.rotor_speeds if obs.rotor_speeds is not None and np.all(np.isfinite(obs.rotor_speeds)) \
            else self._last_speeds
        if self.estimator is not None:
            est = self.estimator.update(obs.imu, obs.gps)
            state = VehicleState(est.xi, speeds, est.quaternion)
        elif obs.truth is not None and np.all(np.isfinite(obs.truth.position)):
            state = VehicleState(obs.truth.xi, speeds, obs.truth.quaternion)
        elif self._last_state is not None:  # a lost truth frame: hold the last one
            state = self._last_state
        else:
            raise UserError("the SITL's first step carried no true state (HIL_STATE_QUATERNION + "
                            "LOCAL_POSITION_NED)", hint="use --state sensors, or check the SITL version")
        self._last_state = state
        return state

    def fly(self, out_dir: str | Path) -> FlightResult:
        """Connect, fly settings.duration [s], write the tlog, step CSV, metrics and figures to out_dir."""
        s = self.settings
        out, files, tlog, log = open_flight_outputs(out_dir)
        client = LockstepClient(hil=s.hil, tlog=tlog, timeout=s.link_timeout)
        n_steps = int(round(s.duration / EXCHANGE_STEP))
        completed = False
        crashed = False
        message = ""
        airborne = False
        interrupted = False
        progress = None
        try:
            obs = client.connect(timeout=s.connect_timeout)
            t0 = obs.t
            self.controller.reset()
            if self.estimator is not None:
                self.estimator.reset()
            if s.progress:
                from tqdm import tqdm

                progress = tqdm(total=n_steps, unit="step", desc=f"{self.controller.name} "
                                f"{getattr(self.trajectory, 'name', '')}", file=sys.stderr, mininterval=0.5,
                                disable=None)  # None: no bar when stderr is not a terminal (a pipe, a log)
            flown: Any = None
            for k in range(n_steps):
                start = time.perf_counter()
                t = obs.t - t0
                state = self.feedback(obs)
                if flown is None:  # the take-off starts where the vehicle stands
                    flown = self.flown = shaped_reference(self.trajectory, state.xi[0:3], float(state.xi[8]),
                                                          s.takeoff, s.governor)
                ref: Reference = flown.reference(t)
                c0 = time.perf_counter()
                cmd = self.controller.update(t, state, ref)
                control = time.perf_counter() - c0
                speeds = np.asarray(cmd.rotor_speeds, dtype=float)
                throttles = [self.curve.throttle_for_speed(float(w)) for w in speeds]
                loop = time.perf_counter() - start
                truth = obs.truth
                if truth is not None:
                    true_row = [*truth.position, *truth.velocity, *truth.euler]
                else:
                    true_row = [math.nan] * 9
                log.add([t, *ref.position, *ref.velocity, ref.yaw, *state.xi, *true_row, *state.rotor_speeds,
                         *speeds, *throttles, float(cmd.saturated), control * 1e6, loop * 1e6])
                height = -(true_row[2] if truth is not None else state.xi[2])
                tilt = _tilt(*(true_row[6:8] if truth is not None else state.xi[6:8]))
                if height > AIRBORNE_HEIGHT:
                    airborne = True
                if (airborne and height < 0.02) or tilt > CRASH_TILT or not np.all(np.isfinite(state.xi)):
                    crashed = True
                    why = "back on the ground" if height < 0.02 else \
                        f"tilt {math.degrees(tilt):.0f} deg" if tilt > CRASH_TILT else "state diverged"
                    message = f"crash at t = {t:.2f} s: {why}"
                    break
                self._last_speeds = speeds
                if progress is not None and (k + 1) % 25 == 0:
                    progress.update(25)
                try:
                    obs = client.step(throttles)
                except LinkLost:
                    message = (f"link lost: no sensor message from the SITL at {s.hil} for "
                               f"{s.link_timeout:g} s (last step t = {t:.3f} s); stopped commanding the "
                               "motors")
                    print(f"quadsr fly: {message}", file=sys.stderr, flush=True)
                    break
            else:
                completed = True
        except KeyboardInterrupt:
            interrupted = True
            message = "interrupted"
        finally:
            if progress is not None:
                progress.close()
            client.close()
            tlog.close()
            log.close()
        stats = vars(client.stats) if hasattr(client.stats, "__dict__") else {}
        metrics = self._finish(log, out, files, completed, crashed)
        if interrupted:  # the outputs of the partial flight are written; now stop as asked
            raise KeyboardInterrupt
        return FlightResult(metrics, completed, crashed, message, len(log.rows), out, files, stats,
                            list(client.status_texts))

    def _finish(self, log: StepLog, out: Path, files: dict[str, Path], completed: bool,
                crashed: bool) -> FlightMetrics | None:
        """Metrics and figures of the logged steps (truth when the SITL sent it, else the fed-back state)."""
        data = log.array()
        if len(data) == 0:
            return None
        has_truth = np.all(np.isfinite(data[:, [_col("true_x"), _col("true_y"), _col("true_z")]]), axis=1)
        use_truth = bool(has_truth.any())
        if use_truth:  # a step whose truth did not arrive is left out, not the whole flight's truth
            data = data[has_truth]
        t = data[:, _col("t")]
        ref_p = data[:, [_col("ref_x"), _col("ref_y"), _col("ref_z")]]
        truth = data[:, [_col("true_x"), _col("true_y"), _col("true_z")]]
        pos = truth if use_truth else data[:, [_col("x"), _col("y"), _col("z")]]
        names = ("true_phi", "true_theta", "true_psi") if use_truth else ("phi", "theta", "psi")
        phi, theta, psi = (data[:, _col(n)] for n in names)
        tilt = np.arccos(np.clip(np.cos(phi) * np.cos(theta), -1.0, 1.0))
        metrics = compute_metrics(
            t, pos, ref_p, psi, data[:, _col("ref_yaw")], data[:, _col("saturated")] > 0.5,
            data[:, _col("control_us")] * 1e-6, controller=self.controller.name,
            trajectory=str(getattr(self.trajectory, "name", "")), completed=completed, crashed=crashed,
            tilt_rad=tilt,
        )
        files["metrics_md"], files["metrics_csv"] = write_metrics(metrics, out)
        if not self.settings.figures:
            return metrics
        from controller.plots import path3d_figure, tracking_figure

        title = f"{flight_label(self.controller)} on {metrics.trajectory}"
        files["tracking"] = tracking_figure(t, pos, ref_p, psi, data[:, _col("ref_yaw")],
                                            out / "tracking.png", title)
        files["path3d"] = path3d_figure(pos, ref_p, out / "path3d.png", title)
        return metrics
