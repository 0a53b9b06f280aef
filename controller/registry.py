"""Controllers selectable by name: backstepping (model-based), pid (PX4-style cascade), se3 (geometric).

A gains file (YAML) is either a flat mapping for the chosen controller, or a mapping with one section per
controller name (`backstepping:`, `pid:`, `se3:`), of which the chosen one is used.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from bridge.errors import UserError
from bridge.vehicle import VehicleConfig
from bridge.yaml_file import load_yaml_file
from controller.plugin import Controller

CONTROLLER_NAMES = ("backstepping", "pid", "se3")
NEEDS_MODEL = ("backstepping",)


def check_controller_name(name: str) -> str:
    """The name if it is a known controller, else a UserError listing the choices."""
    if name not in CONTROLLER_NAMES:
        raise UserError(f"unknown controller {name!r}", hint=f"choose one of {', '.join(CONTROLLER_NAMES)}")
    return name


def read_gains_file(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The mapping in a gains YAML file (empty file: {}); UserError if unreadable or not a mapping."""
    p = Path(path)
    if not p.exists():
        raise UserError(f"gains file {p} does not exist")
    data = load_yaml_file(p, f"gains file {p}")
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise UserError(f"gains file {p}: expected a mapping of gain names to values")
    return data


def gains_for(name: str, gains: dict[str, Any] | str | os.PathLike[str] | None) -> tuple[dict[str, Any], str]:
    """The gain mapping for controller `name` (from a mapping or a file) and a label naming its source."""
    if gains is None:
        return {}, f"{name} gains"
    if isinstance(gains, (str, os.PathLike)):
        where = str(gains)
        data = read_gains_file(gains)
    else:
        where = "gains"
        data = dict(gains)
    sections = [k for k in data if k in CONTROLLER_NAMES]
    if sections:
        other = [k for k in data if k not in CONTROLLER_NAMES]
        if other:
            raise UserError(f"{where}: mixes controller sections ({', '.join(sections)}) with flat keys "
                            f"({', '.join(map(str, other))})",
                            hint="either one flat mapping for the chosen controller, or one section per "
                                 "controller")
        section = data.get(name) or {}
        if not isinstance(section, dict):
            raise UserError(f"{where}: section {name!r} must be a mapping of gain names to values")
        return section, f"{where} [{name}]"
    return data, where


def make_controller(
    name: str,
    model: Any = None,
    vehicle: VehicleConfig | None = None,
    gains: dict[str, Any] | str | os.PathLike[str] | None = None,
) -> Controller:
    """Build controller `name` for a vehicle (and a model: a Model or a model file path, for backstepping).

    Raises UserError for an unknown name, a missing or non-invertible model, or bad gains.
    """
    check_controller_name(name)
    if vehicle is None:
        from bridge.vehicle import load_vehicle

        vehicle = load_vehicle("fang-chen-buaa")
    values, where = gains_for(name, gains)
    if name == "pid":
        from controller.baselines.pid_cascade import PidCascadeController, PidCascadeGains

        return PidCascadeController(vehicle, PidCascadeGains.from_mapping(values, where))
    if name == "se3":
        from controller.baselines.se3 import Se3Controller, Se3Gains

        return Se3Controller(vehicle, Se3Gains.from_mapping(values, where))
    if model is None:
        raise UserError("the backstepping controller needs a model file",
                        hint="give --model FILE (a learned model.yaml, or the true model from "
                             "`quadsr model-from-vehicle`)")
    if isinstance(model, (str, os.PathLike)):
        from identification.model_file import load_model

        model = load_model(model)
    from controller.backstepping import BacksteppingController
    from controller.gains import gains_from_dict

    return BacksteppingController(model, vehicle, gains_from_dict(values, where))
