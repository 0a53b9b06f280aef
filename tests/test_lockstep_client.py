"""bridge.lockstep.LockstepClient against a tiny SITL stand-in speaking real UDP/MAVLink in a thread."""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest

from bridge import messages as M
from bridge.link import Endpoint, UdpLink
from bridge.lockstep import LinkLost, LockstepClient
from bridge.vehicle import MotorCurve


class FakeSitl:
    """Answers like the SITL: time-0 step after a companion speaks (re-sent every 0.1 s until the first
    actuator message), then one step per HIL_ACTUATOR_CONTROLS answering the last HIL_SENSOR."""

    def __init__(self, answer: bool = True, extra_resends: int = 0):
        self.link = UdpLink(Endpoint("127.0.0.1", 0), None, 1, 51)
        self.address = f"udp:127.0.0.1:{self.link.local.port}"
        self.answer = answer
        self.extra_resends = extra_resends  # duplicate time-0 datagrams sent right after the first one
        self.commands: list[M.ActuatorCommand] = []
        self.heartbeats = 0
        self.t = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> FakeSitl:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(5)
        self.link.close()

    def _send_step(self) -> None:
        t = self.t
        state = M.TrueState.from_quaternion(
            t, (0.0, 0.0, -t * 1e-6), (0.0, 0.0, -1.0), (1, 0, 0, 0), (0, 0, 0)
        )
        self.link.send(
            [
                M.encode_hil_state_quaternion(state, 47.0, 8.0, 500.0),
                M.encode_local_position_ned(state),
                M.encode_raw_rpm([557.0 + t * 1e-3] * 4),
                M.encode_hil_sensor(M.ImuSample(t, (0.0, 0.0, -9.8), (0.0, 0.0, 0.0))),
            ]
        )

    def _run(self) -> None:
        started = False
        next_resend = 0.0
        while not self._stop.is_set():
            for m in self.link.recv(0.02):
                kind = m.get_type()
                if kind == "HEARTBEAT":
                    self.heartbeats += 1
                    if not started:
                        started = True
                        self._send_step()
                        for _ in range(self.extra_resends):
                            self._send_step()
                        next_resend = time.monotonic() + 0.1
                elif kind == "HIL_ACTUATOR_CONTROLS" and self.answer and m.time_usec == self.t:
                    self.commands.append(M.decode_hil_actuator_controls(m))
                    self.t += 4000
                    self._send_step()
            if started and not self.commands and self.answer and time.monotonic() > next_resend:
                self._send_step()  # the time-0 re-send
                next_resend = time.monotonic() + 0.1


def test_connect_then_step_returns_each_next_step():
    with FakeSitl(extra_resends=3) as sitl, LockstepClient(sitl.address, timeout=2.0) as client:
        first = client.connect(timeout=5.0)
        assert first.time_usec == 0 and first.t == 0.0
        assert first.truth is not None and first.rotor_speeds is not None
        assert sitl.heartbeats >= 1
        times = [client.step([0.5, 0.5, 0.5, 0.5]).time_usec for _ in range(20)]
        assert times == [4000 * (k + 1) for k in range(20)]  # the duplicated time-0 steps were skipped
        obs = client.observation
        np.testing.assert_allclose(obs.truth.position, [0.0, 0.0, -0.08], atol=1e-6)
        np.testing.assert_allclose(obs.rotor_speeds, [637.0] * 4, rtol=1e-6)  # 557 + t in ms
        cmd = sitl.commands[0]
        assert cmd.time_usec == 0 and cmd.lockstep and cmd.mode == M.ARMED_MODE
        assert [c.time_usec for c in sitl.commands] == [4000 * k for k in range(20)]
        assert client.steps == 20 and client.stats.dropped == 0
        assert client.stats.frames_received >= 21 * 7


def test_throttles_are_cleaned_before_sending():
    with FakeSitl() as sitl, LockstepClient(sitl.address, timeout=2.0) as client:
        client.connect(5.0)
        client.step([math.nan, 1.5, -0.2, 0.25])
        np.testing.assert_allclose(sitl.commands[0].throttles, [0.0, 1.0, 0.0, 0.25])
        client.step([math.inf, -math.inf, 1.0, 0.0])  # +inf is 0 (motor off), as the SITL takes it
        np.testing.assert_allclose(sitl.commands[1].throttles, [0.0, 0.0, 1.0, 0.0])
        with pytest.raises(ValueError):
            client.step([0.5, 0.5])


def test_step_speeds_uses_the_motor_curve():
    curve = MotorCurve(1148.0, -141.4)
    with FakeSitl() as sitl, LockstepClient(sitl.address, timeout=2.0) as client:
        client.connect(5.0)
        client.step_speeds([557.1, 0.0, 1006.6, 300.0], curve)
        expected = [curve.throttle_for_speed(w) for w in (557.1, 0.0, 1006.6, 300.0)]
        np.testing.assert_allclose(sitl.commands[0].throttles, expected, rtol=1e-6)


def test_connect_without_a_sitl_raises_link_lost():
    silent = UdpLink(Endpoint("127.0.0.1", 0))  # a bound port that never answers
    try:
        client = LockstepClient(f"udp:127.0.0.1:{silent.local.port}", timeout=0.2)
        start = time.monotonic()
        with pytest.raises(LinkLost, match="no SITL answered"):
            client.connect(timeout=0.3)
        assert 0.25 < time.monotonic() - start < 2.0
        assert client.stats.frames_sent >= 3  # heartbeats every 0.1 s
        client.close()
    finally:
        silent.close()


def test_step_raises_link_lost_when_the_sitl_stops_answering():
    with FakeSitl() as sitl, LockstepClient(sitl.address, timeout=5.0) as client:
        client.connect(5.0)
        client.step([0.5] * 4)  # answered (a patient bound: the fake SITL's thread may be slow to run)
        sitl.answer = False
        client.timeout = 0.2
        start = time.monotonic()
        with pytest.raises(LinkLost, match="no step"):
            client.step([0.5] * 4)
        assert 0.15 < time.monotonic() - start < 1.5
