"""The campaign file (YAML): what to fly, over which grid and Monte-Carlo draws; read and checked once here.

A campaign file names a nominal vehicle (controllers and models are built for it), a pipeline (`fly`: fly each
task with a controller; `learn-fly`: each task first flies an excitation on its own vehicle, identifies a
model and flies the controller derived from it), `grid:` lists whose every combination is flown, `fixed:`
values shared by every task, and `random:` distributions drawn `samples` times (the same draws for every
grid point, so controllers are compared on the same vehicles and winds). See README.md, "Campaigns".
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bridge.errors import UserError
from bridge.vehicle import load_vehicle, resolve_vehicle_path
from bridge.yaml_file import Section, describe_value, float_value, load_yaml_file

PIPELINES = ("fly", "learn-fly")
CONTROLLERS = ("backstepping-learned", "backstepping-true", "pid", "se3")
STATES = ("truth", "sensors")
SENSOR_PRESETS = ("ideal", "realistic")
TURBULENCE = ("none", "light", "moderate", "severe")
DISTRIBUTIONS = ("uniform", "normal", "log_uniform", "choice", "scale")

# The task parameters that are not vehicle-file keys: name -> (kind, default, what it is).
FLIGHT_PARAMETERS: dict[str, tuple[str, Any, str]] = {
    "trajectory": ("text", "case1", "trajectory name or file (controller/trajectories)"),
    "controller": ("text", "backstepping-true", "one of " + ", ".join(CONTROLLERS)),
    "state": ("text", "truth", "state fed back: truth | sensors"),
    "sensors": ("text", "ideal", "SITL sensor preset: ideal | realistic"),
    "duration": ("number", 12.0, "s simulated per tracking flight"),
    "wind_speed": ("number", 0.0, "m/s, steady horizontal wind speed"),
    "wind_direction": ("number", 0.0, "rad, direction the air moves towards, from north (NED), clockwise"),
    "wind_down": ("number", 0.0, "m/s, steady vertical wind, NED (positive down)"),
    "turbulence": ("text", "none", "Dryden turbulence preset: none | light | moderate | severe"),
    "profile": ("text", "closed-loop", "learn-fly: the excitation profile each task flies"),
    "learn_duration": ("number", 30.0, "learn-fly: s simulated of the excitation flight"),
}
ALWAYS = ("trajectory", "controller", "state", "sensors", "duration")  # in every task's row
LEARN_ONLY = ("profile", "learn_duration")  # in every learn-fly task's row
TEXT_CHOICES = {"controller": CONTROLLERS, "state": STATES, "sensors": SENSOR_PRESETS,
                "turbulence": TURBULENCE}


@dataclass(frozen=True)
class Distribution:
    """One random parameter: kind (uniform | normal | log_uniform | choice | scale) and its arguments."""

    kind: str
    args: tuple[Any, ...]

    def describe(self) -> str:
        """Short text, e.g. 'uniform(0, 6)' or 'x uniform(0.8, 1.2)'."""
        inner = ", ".join(f"{a:g}" if isinstance(a, float) else str(a) for a in self.args)
        return f"x uniform({inner})" if self.kind == "scale" else f"{self.kind}({inner})"


@dataclass(frozen=True)
class LearnedModelSpec:
    """Where backstepping-learned's model comes from: a file, or an excitation on the nominal vehicle."""

    path: Path | None = None
    profile: str = "closed-loop"
    duration: float = 30.0  # s simulated
    seed: int = 0


@dataclass(frozen=True)
class CampaignSpec:
    """A checked campaign file (see the module doc)."""

    name: str
    source: Path
    seed: int
    vehicle: str  # the nominal vehicle file's path
    pipeline: str
    grid: dict[str, tuple[Any, ...]]
    fixed: dict[str, Any]
    random: dict[str, Distribution]
    samples: int
    learned_model: LearnedModelSpec
    identify_budget: int = 60  # SR generations per target (learn-fly, the learned model): iterations
    keep_flights: bool = False  # copy each task's flight folder to OUT/flights/<task id>
    vehicle_keys: tuple[str, ...] = field(default=())  # the parameters that are vehicle-file keys
    trajectory_files: dict[str, str] = field(default_factory=dict)  # trajectory value -> its file's text

    @property
    def task_count(self) -> int:
        """How many tasks the campaign has: the grid's combinations times the samples."""
        n = self.samples
        for values in self.grid.values():
            n *= len(values)
        return n

    def parameter_names(self) -> list[str]:
        """Every parameter a task row carries, in a stable order (grid, fixed, random; flight ones first)."""
        names = list(dict.fromkeys([*self.defaults(), *self.grid, *self.fixed, *self.random]))
        return sorted(names, key=lambda n: (n in self.vehicle_keys, n))

    def defaults(self) -> dict[str, Any]:
        """The parameters every task carries, at their defaults (what grid, fixed and random override)."""
        names = ALWAYS + (LEARN_ONLY if self.pipeline == "learn-fly" else ())
        return {n: FLIGHT_PARAMETERS[n][1] for n in names}

    def nominal_values(self) -> dict[str, Any]:
        """The nominal vehicle file's value of every varied vehicle key (what `scale` multiplies)."""
        data = load_yaml_file(Path(self.vehicle), f"vehicle file {self.vehicle}")
        return {key: _vehicle_value(data, key) for key in self.vehicle_keys}

    @property
    def needs_learned_model(self) -> bool:
        """Whether some task flies backstepping on the model learned once on the nominal vehicle."""
        if self.pipeline != "fly":
            return False
        controllers = set(self.grid.get("controller", ()))
        controllers |= {self.fixed["controller"]} if "controller" in self.fixed else set()
        if "controller" in self.random:
            controllers |= set(self.random["controller"].args)
        if not controllers:
            controllers = {FLIGHT_PARAMETERS["controller"][1]}
        return "backstepping-learned" in controllers


def _vehicle_value(data: Any, dotted: str) -> Any:
    """The value at a dotted key of the vehicle file's mapping, or raise KeyError."""
    node = data
    for part in dotted.split("."):
        if not isinstance(node, dict) or part not in node:
            raise KeyError(dotted)
        node = node[part]
    return node


def _check_value(where: str, key: str, name: str, value: Any, vehicle_data: Any) -> Any:
    """A fixed or grid value for parameter `name`, checked (numbers finite, texts among the choices)."""
    if name in FLIGHT_PARAMETERS:
        kind = FLIGHT_PARAMETERS[name][0]
        if kind == "number":
            out = float_value(where, key, value)
            if name in ("duration", "learn_duration") and out <= 0:
                raise UserError(f"{where}: key '{key}' must be > 0 s, got {value}")
            if name == "wind_speed" and out < 0:
                raise UserError(f"{where}: key '{key}' must be >= 0 m/s, got {value}",
                                hint="give the direction in wind_direction")
            return out
        if not isinstance(value, str) or not value:
            raise UserError(f"{where}: key '{key}' must be a text, got {describe_value(value)}")
        choices = TEXT_CHOICES.get(name)
        if choices and value not in choices:
            raise UserError(f"{where}: key '{key}' must be one of {', '.join(choices)}, got {value!r}")
        return value
    nominal = _vehicle_value(vehicle_data, name)
    if isinstance(nominal, list):
        if not isinstance(value, list) or len(value) != len(nominal):
            raise UserError(f"{where}: key '{key}' must be a list of {len(nominal)} numbers like the "
                            f"vehicle file's {name}, got {describe_value(value)}")
        return tuple(float_value(where, f"{key}[{i}]", v) for i, v in enumerate(value))
    if isinstance(nominal, (int, float)) and not isinstance(nominal, bool):
        return float_value(where, key, value)
    if isinstance(nominal, str):
        if not isinstance(value, str):
            raise UserError(f"{where}: key '{key}' must be a text, got {describe_value(value)}")
        return value
    raise UserError(f"{where}: key '{key}': vehicle key {name!r} is a section, not a value",
                    hint="name a value inside it, e.g. motor.time_constant")


def _check_name(where: str, key: str, name: Any, vehicle_data: Any, vehicle: str) -> str:
    if not isinstance(name, str):
        raise UserError(f"{where}: key '{key}' has a parameter name that is not a text: {name!r}")
    if name in FLIGHT_PARAMETERS:
        return name
    try:
        _vehicle_value(vehicle_data, name)
    except KeyError:
        raise UserError(f"{where}: unknown parameter '{key}'",
                        hint=f"flight parameters: {', '.join(FLIGHT_PARAMETERS)}; or a key of the vehicle "
                             f"file {vehicle} (dotted, e.g. mass, motor.time_constant)") from None
    return name


def _distribution(where: str, key: str, name: str, value: Any, vehicle_data: Any) -> Distribution:
    if not isinstance(value, dict) or len(value) != 1:
        raise UserError(f"{where}: key '{key}' must be a one-key mapping such as {{uniform: [0, 6]}}, got "
                        f"{describe_value(value)}", hint=f"distributions: {', '.join(DISTRIBUTIONS)}")
    kind, args = next(iter(value.items()))
    if kind not in DISTRIBUTIONS:
        raise UserError(f"{where}: key '{key}': unknown distribution {kind!r}",
                        hint=f"choose one of {', '.join(DISTRIBUTIONS)}")
    k = f"{key}.{kind}"
    if kind == "choice":
        if not isinstance(args, list) or not args:
            raise UserError(f"{where}: key '{k}' must be a non-empty list of values")
        return Distribution(kind, tuple(_check_value(where, f"{k}[{i}]", name, a, vehicle_data)
                                        for i, a in enumerate(args)))
    if not isinstance(args, list) or len(args) != 2:
        raise UserError(f"{where}: key '{k}' must be a list of two numbers, got {describe_value(args)}")
    a, b = (float_value(where, f"{k}[{i}]", v) for i, v in enumerate(args))
    if kind == "normal":
        if b < 0:
            raise UserError(f"{where}: key '{k}': the standard deviation must be >= 0, got {b}")
    elif a > b:
        raise UserError(f"{where}: key '{k}': the low end {a} is above the high end {b}")
    if kind == "log_uniform" and a <= 0:
        raise UserError(f"{where}: key '{k}': log_uniform needs positive bounds, got {a}")
    if kind == "scale":
        if name in FLIGHT_PARAMETERS:
            raise UserError(f"{where}: key '{k}': scale multiplies a vehicle-file value; {name!r} is a "
                            "flight parameter", hint="use uniform for flight parameters")
        nominal = _vehicle_value(vehicle_data, name)
        if isinstance(nominal, str):
            raise UserError(f"{where}: key '{k}': vehicle key {name!r} is a text and cannot be scaled")
    elif name not in FLIGHT_PARAMETERS and isinstance(_vehicle_value(vehicle_data, name), list):
        raise UserError(f"{where}: key '{k}': vehicle key {name!r} is a list; vary it with scale",
                        hint="e.g. {scale: [0.85, 1.15]}")
    elif name in FLIGHT_PARAMETERS and FLIGHT_PARAMETERS[name][0] != "number":
        raise UserError(f"{where}: key '{k}': {name!r} is a text parameter; draw it with choice")
    return Distribution(kind, (a, b))


def _learned_model(where: str, base: Path, value: Any) -> LearnedModelSpec:
    if value is None:
        return LearnedModelSpec()
    if isinstance(value, str):
        path = (base / value).resolve() if not Path(value).is_absolute() else Path(value)
        if not path.is_file():
            raise UserError(f"{where}: key 'models.learned': model file {path} does not exist",
                            hint="give a model.yaml path (relative to the campaign file) or an excitation "
                                 "mapping {profile, duration, seed}")
        return LearnedModelSpec(path=path)
    if not isinstance(value, dict):
        raise UserError(f"{where}: key 'models.learned' must be a model file path or a mapping")
    sec = Section(where, value, "models.learned")
    spec = LearnedModelSpec(None, sec.text("profile", default="closed-loop"),
                            sec.number("duration", 30.0, positive=True), sec.integer("seed", 0))
    sec.done()
    return spec


MIN_TURBULENT_WIND = 0.1  # m/s, the smallest mean wind the SITL accepts with Dryden turbulence


def _lowest(dist: Distribution) -> float:
    """The smallest value a wind-speed distribution can draw (normal: mean - 4 std)."""
    if dist.kind == "choice":
        return min(float(v) for v in dist.args)
    a, b = dist.args
    return a - 4.0 * b if dist.kind == "normal" else a




def load_campaign(path: str | Path) -> CampaignSpec:
    """Read and check a campaign file; every mistake is a UserError naming the file and key."""
    p = Path(path)
    where = f"campaign file {p}"
    if p.is_dir():
        raise UserError(f"{where} is a directory", hint="give the campaign's YAML file")
    if not p.is_file():
        raise UserError(f"{where} does not exist", hint="see README.md, 'Campaigns', for an example")
    data = load_yaml_file(p, where)
    if not isinstance(data, dict):
        raise UserError(f"{where}: expected a mapping of campaign keys, got {describe_value(data)}")
    top = Section(where, data, hint="see README.md, 'Campaigns', for every key")
    name = top.text("name", default=p.stem)
    seed = top.integer("seed", 0)
    vehicle_ref = str(top.raw("vehicle", "fang-chen-buaa"))
    local = (p.parent / vehicle_ref)
    vehicle_path = local.resolve() if local.is_file() else resolve_vehicle_path(vehicle_ref)
    load_vehicle(vehicle_path)  # checks it
    vehicle_data = load_yaml_file(vehicle_path, f"vehicle file {vehicle_path}")
    pipeline = top.text("pipeline", PIPELINES, default="fly")
    grid_sec, fixed_sec, random_sec = (top.optional_section(k) for k in ("grid", "fixed", "random"))
    models_sec = top.optional_section("models")
    samples = top.integer("samples", 1, low=1)
    budget = top.integer("identify_budget", 60, low=1)
    keep = top.flag("keep_flights", False)
    top.raw("description", "")
    top.done()

    grid: dict[str, tuple[Any, ...]] = {}
    for raw, values in grid_sec.data.items():
        n = _check_name(where, f"grid.{raw}", raw, vehicle_data, vehicle_ref)
        if not isinstance(values, list) or not values:
            raise UserError(f"{where}: key 'grid.{n}' must be a non-empty list of values")
        checked = tuple(_check_value(where, f"grid.{n}[{i}]", n, v, vehicle_data)
                        for i, v in enumerate(values))
        if len(set(checked)) != len(checked):
            raise UserError(f"{where}: key 'grid.{n}' lists a value twice")
        grid[n] = checked
    fixed = {}
    for raw, value in fixed_sec.data.items():
        n = _check_name(where, f"fixed.{raw}", raw, vehicle_data, vehicle_ref)
        fixed[n] = _check_value(where, f"fixed.{n}", n, value, vehicle_data)
    random = {}
    for raw, value in random_sec.data.items():
        n = _check_name(where, f"random.{raw}", raw, vehicle_data, vehicle_ref)
        random[n] = _distribution(where, f"random.{n}", n, value, vehicle_data)
    for n in grid:
        if n in fixed or n in random:
            raise UserError(f"{where}: parameter '{n}' is both in 'grid' and in "
                            f"'{'fixed' if n in fixed else 'random'}'", hint="give it in one place")
    for n in fixed:
        if n in random:
            raise UserError(f"{where}: parameter '{n}' is both in 'fixed' and in 'random'")
    if random and "samples" not in data:
        raise UserError(f"{where}: 'random' is given but 'samples' is not",
                        hint="say how many Monte-Carlo draws to fly, e.g. samples: 25")
    turbulence = {*grid.get("turbulence", ()), fixed.get("turbulence", "none")}
    if "turbulence" in random:
        turbulence |= set(random["turbulence"].args)
    speeds = {*grid.get("wind_speed", ()), fixed.get("wind_speed", 0.0)}
    if turbulence - {"none"} and speeds == {0.0} and "wind_speed" not in random:
        raise UserError(f"{where}: turbulence is asked for without a wind speed",
                        hint="Dryden turbulence scales with the mean wind: give wind_speed > 0")
    if turbulence - {"none"}:  # the SITL refuses Dryden turbulence below MIN_TURBULENT_WIND m/s
        low = min(speeds) if "wind_speed" not in random else _lowest(random["wind_speed"])
        where_key = "random.wind_speed" if "wind_speed" in random else "grid/fixed wind_speed"
        if low < MIN_TURBULENT_WIND:
            raise UserError(f"{where}: key '{where_key}' can be {low:g} m/s with turbulence asked for",
                            hint=f"Dryden turbulence needs a mean wind of at least {MIN_TURBULENT_WIND} m/s "
                                 "(its time scale): start the range there, or fly still air without it")
    learned = _learned_model(where, p.parent, models_sec.raw("learned", None))
    models_sec.done()
    names = {*grid, *fixed, *random}
    vehicle_keys = tuple(sorted(n for n in names if n not in FLIGHT_PARAMETERS))
    trajectories = [*grid.get("trajectory", ()), fixed.get("trajectory", FLIGHT_PARAMETERS["trajectory"][1])]
    if "trajectory" in random:
        trajectories += list(random["trajectory"].args)
    files = {t: _trajectory_text(where, p.parent, t) for t in dict.fromkeys(trajectories)}
    return CampaignSpec(name, p.resolve(), seed, str(vehicle_path), pipeline, grid, fixed, random, samples,
                        learned, budget, keep, vehicle_keys,
                        {t: text for t, text in files.items() if text is not None})


def _trajectory_text(where: str, base: Path, value: str) -> str | None:
    """None for a built-in trajectory name; else the checked text of the file (relative to the campaign)."""
    from controller.trajectories import BUILTIN, load_trajectory

    if value in BUILTIN:
        return None
    path = Path(value) if Path(value).is_absolute() else base / value
    if not path.is_file():
        raise UserError(f"{where}: trajectory {value!r} is neither a built-in name nor a file next to the "
                        "campaign file", hint=f"built-in: {', '.join(BUILTIN)}; or a trajectory YAML file")
    load_trajectory(path)  # checks it
    return path.read_text()
