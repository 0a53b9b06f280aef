"""A real MAVSDK-Python 4.x client on the SITL's offboard link sees the simulated position and attitude."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from mavsdk import ComponentType, Configuration, Mavsdk
from mavsdk.plugins.telemetry import Telemetry

from bridge.lockstep import LockstepClient

pytestmark = pytest.mark.e2e


class Latest:
    """The newest value of each subscribed telemetry stream (MAVSDK calls back from its own thread)."""

    def __init__(self) -> None:
        self.values: dict[str, object] = {}
        self.lock = threading.Lock()

    def setter(self, name: str):
        def store(value, _user_data) -> None:
            with self.lock:
                self.values[name] = value

        return store

    def get(self, name: str):
        with self.lock:
            return self.values.get(name)


def expect_match(latest: Latest, obs, timeout: float = 3.0) -> None:
    """Wait until MAVSDK's newest position/attitude equal the simulated state of obs (float32 precision)."""
    deadline = time.monotonic() + timeout
    while True:
        pv, euler, q = latest.get("pv"), latest.get("euler"), latest.get("q")
        try:
            assert pv is not None and euler is not None and q is not None
            pos = (pv.position.north_m, pv.position.east_m, pv.position.down_m)
            vel = (pv.velocity.north_m_s, pv.velocity.east_m_s, pv.velocity.down_m_s)
            assert pos == pytest.approx(obs.truth.position, abs=1e-4)
            assert vel == pytest.approx(obs.truth.velocity, abs=1e-4)
            assert (q.w, q.x, q.y, q.z) == pytest.approx(obs.truth.quaternion, abs=1e-5)
            angles = np.radians([euler.roll_deg, euler.pitch_deg, euler.yaw_deg])
            assert angles == pytest.approx(obs.truth.euler, abs=1e-4)
            return
        except AssertionError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.05)


def test_mavsdk_reads_the_simulated_position_and_attitude(start_sitl, udp_port):
    sitl = start_sitl("--no-gcs", "--offboard", f"udp:127.0.0.1:{udp_port}", "--sensors", "ideal",
                      "--lockstep-timeout", "10")
    drone = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
    try:
        drone.add_any_connection(f"udpin://0.0.0.0:{udp_port}")
        system = drone.first_autopilot(10.0)  # the SITL's heartbeats at wall-clock pace, before any companion
        assert system is not None and system.is_connected()
        telemetry = Telemetry(system)
        latest = Latest()
        telemetry.subscribe_position_velocity_ned(latest.setter("pv"))
        telemetry.subscribe_attitude_euler(latest.setter("euler"))
        telemetry.subscribe_attitude_quaternion(latest.setter("q"))
        with LockstepClient(sitl.hil, timeout=5.0) as client:
            client.connect(10.0)
            # Take off nose-up, then yaw: every state in the comparison differs from zero. Stopping on a
            # multiple of 5 steps makes the last ground-link sample (50 Hz of simulated time) the last step.
            for _ in range(150):
                obs = client.step([0.66, 0.65, 0.66, 0.65])
            expect_match(latest, obs)
            assert obs.truth.position[2] < -0.1 and obs.truth.euler[1] > 0.1
            for _ in range(100):
                obs = client.step([0.68, 0.68, 0.66, 0.66])
            expect_match(latest, obs)
            assert abs(obs.truth.euler[2]) > 0.01 and obs.truth.position[0] < -0.5
        assert telemetry.attitude_euler().pitch_deg == pytest.approx(np.degrees(obs.truth.euler[1]), abs=1e-3)
    finally:
        drone.destroy()
