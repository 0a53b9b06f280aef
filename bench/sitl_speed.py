"""How fast the SITL steps: physics alone, the bare MAVLink messaging ceiling, and the full SITL in lockstep,
for both bundled vehicles: fang-chen-buaa (the paper's physics) and fang-chen-aero with every effect on
(rotor drag, translational lift, frame drag, ground effect, CG offset, PX4 thrust model, plus here motor speed
noise 10 rad/s and wind: 5 m/s steady, moderate Dryden turbulence, a 1-cosine gust, WIND_COV sent each step).

Prints, each as the median of --repeats runs:
  physics       Quadrotor.step + SensorModel.sample, no MAVLink (steps/s; floor 20,000 with every effect on),
                the compiled derivative where it is built (QUADSR_PHYSICS=python: the Python one),
                also by the process's CPU time (what the machine's load changes least)
  ceiling       (the faster of: sleeping for each datagram; polling up to bridge.link.LOCKSTEP_SPIN_S first)
                a bare pymavlink HIL_SENSOR -> HIL_ACTUATOR_CONTROLS ping-pong between two processes over
                loopback UDP (round trips/s): what one lockstep exchange can cost at best
  full          `quadsr sitl` in lockstep with a trivial companion (bridge.lockstep.LockstepClient, constant
                throttles) (steps/s)
  full/ceiling  the ratio (floor 0.5), and full >= 5000 steps/s (floor), for each vehicle
It also prints the CPU time per step of the SITL process and of the companion (and the kernel's share of each:
system time), their sum over the ceiling's CPU time per round trip (both of its processes): what a loaded
machine changes least, and PASS only when every floor holds for both vehicles. And the SITL's context switches
per step: ~1 involuntary when the companion is woken on the SITL's core and runs at once, ~1 voluntary when
the SITL sleeps for each reply (the companion ran on the other core, or other processes ran in between; with
the two pinned to different cores on a loaded machine both took about twice the CPU per step).

Usage: python bench/sitl_speed.py [--steps 20000] [--repeats 3]
"""

from __future__ import annotations

import argparse
import os
import re
import socket
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from bridge.link import LOCKSTEP_SPIN_S  # noqa: E402

ECHO_READY = "echo ready"


VEHICLES = ("fang-chen-buaa", "fang-chen-aero")
AERO_WIND_FLAGS = ("--wind", "5,0,0", "--turbulence", "moderate", "--gust", "1,2,0,3,0",
                   "--initial-position", "0,0,-2000")  # airborne for the whole run


def bench_vehicle(name: str):
    """The vehicle as benchmarked: the paper's in free space; the aero one with ground, noise and wind on."""
    import dataclasses

    from bridge.airframe import GustConfig, wind_config
    from bridge.vehicle import load_vehicle

    if name != "fang-chen-aero":
        return load_vehicle(name).with_overrides(ground="none", initial_position=(0, 0, -100.0))
    wind = wind_config("bench", (5.0, 0.0, 0.0), "moderate", 10.0, (GustConfig(1.0, 2.0, (0.0, 3.0, 0.0)),))
    # high enough to stay airborne through the run (the ground effect is still computed every step)
    vehicle = load_vehicle(name).with_overrides(ground="plane", initial_position=(0, 0, -2000.0), wind=wind)
    return dataclasses.replace(vehicle, motor=dataclasses.replace(vehicle.motor, speed_noise=10.0))


def physics_rate(steps: int, name: str = "fang-chen-buaa") -> tuple[float, float]:
    """(steps/s by wall time, steps/s by this process's CPU time) of Quadrotor.step + SensorModel.sample alone
    (realistic sensors). The CPU-time rate depends less on the machine's load."""
    from sitl.dynamics import Quadrotor
    from sitl.sensors import SensorModel

    vehicle = bench_vehicle(name)
    quad = Quadrotor(vehicle)
    sensors = SensorModel(vehicle.sensors, vehicle.home, 0)
    throttles = (0.6, 0.61, 0.6, 0.61)
    t0, c0 = time.perf_counter(), time.process_time()
    for _ in range(steps):
        quad.step(throttles)
        sensors.sample(quad)
    return steps / (time.perf_counter() - t0), steps / (time.process_time() - c0)


def _polled_recv(sock: socket.socket, seconds: float) -> bytes:
    """sock's next datagram, polled for up to seconds (wall) before a blocking wait (as bridge.link's lockstep
    links wait; seconds 0: block at once)."""
    end = time.monotonic() + seconds
    while seconds > 0.0:
        try:
            return sock.recv(65535, socket.MSG_DONTWAIT)
        except BlockingIOError:
            if time.monotonic() >= end:
                break
            os.sched_yield()
    return sock.recv(65535)


def echo_server(spin: float = 0.0) -> None:
    """The ping-pong's other process: answer each HIL_SENSOR with HIL_ACTUATOR_CONTROLS (bare pymavlink),
    polling for each datagram up to spin s before sleeping for it."""
    from pymavlink.dialects.v20 import common as mavlink

    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    print(f"{ECHO_READY} {sock.getsockname()[1]}", flush=True)
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    mav.robust_parsing = True
    controls = [0.6] * 4 + [0.0] * 12
    addr = None
    while True:
        if addr is None:
            data, addr = sock.recvfrom(65535)
        else:
            data = _polled_recv(sock, spin)
        if data == b"quit":
            return
        for msg in mav.parse_buffer(data) or []:
            if msg.get_msgId() == mavlink.MAVLINK_MSG_ID_HIL_SENSOR:
                reply = mavlink.MAVLink_hil_actuator_controls_message(msg.time_usec, controls, 129, 1)
                sock.sendto(reply.pack(mav), addr)
                mav.seq = (mav.seq + 1) % 256


def ceiling_rate(steps: int, spin: float = 0.0) -> tuple[float, float]:
    """(round trips/s, CPU us per round trip of both processes) of a bare pymavlink HIL_SENSOR /
    HIL_ACTUATOR_CONTROLS ping-pong with a second process; spin: both poll for each datagram up to spin s
    before sleeping for it (as the lockstep links do)."""
    from pymavlink.dialects.v20 import common as mavlink

    proc = subprocess.Popen([sys.executable, __file__, "--echo", "--echo-spin", repr(spin)],
                            stdout=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        port = int(line.split()[-1])
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind(("127.0.0.1", 0))
        sock.connect(("127.0.0.1", port))
        mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=51)
        mav.robust_parsing = True
        echo0, own0, t0 = _cpu_seconds(proc.pid), time.process_time(), time.perf_counter()
        for k in range(steps):
            t = k * 4000
            sensor = mavlink.MAVLink_hil_sensor_message(
                t, 0.01, -0.02, -9.8, 0.001, 0.002, 0.003, 0.2, 0.01, 0.43, 955.0, 0.0, 488.0, 12.0, 0x3F, 0
            )
            sock.send(sensor.pack(mav))
            mav.seq = (mav.seq + 1) % 256
            got = False
            while not got:
                for msg in mav.parse_buffer(_polled_recv(sock, spin)) or []:
                    got = got or (msg.get_msgId() == mavlink.MAVLINK_MSG_ID_HIL_ACTUATOR_CONTROLS
                                  and msg.time_usec == t)
        rate = steps / (time.perf_counter() - t0)
        cpu = (_cpu_seconds(proc.pid) - echo0 + time.process_time() - own0) / steps * 1e6
        sock.send(b"quit")
        sock.close()
        return rate, cpu
    finally:
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            proc.kill()


def _cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process, s (Linux /proc)."""
    return sum(_cpu_times(pid))


def _cpu_times(pid: int) -> tuple[float, float]:
    """(user, system) CPU time of a process, s (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    tick = os.sysconf("SC_CLK_TCK")
    return int(fields[11]) / tick, int(fields[12]) / tick


def _context_switches(pid: int) -> tuple[int, int]:
    """(voluntary, involuntary) context switches of a process so far (Linux /proc)."""
    counts = dict(line.split(":") for line in Path(f"/proc/{pid}/status").read_text().splitlines()
                  if line.endswith(tuple("0123456789")) and "ctxt_switches" in line)
    return int(counts["voluntary_ctxt_switches"]), int(counts["nonvoluntary_ctxt_switches"])


def full_rate(steps: int, extra: tuple[str, ...] = (), spin: bool = True) -> dict[str, float]:
    """`quadsr sitl` in lockstep with a LockstepClient: full (steps/s), sitl_cpu and client_cpu (CPU us/step),
    sitl_sys and client_sys (of these, the kernel's: system time), sitl_vol and sitl_invol (the SITL's
    voluntary and involuntary context switches per step). spin False: neither process polls for the other's
    datagram before sleeping for it (`quadsr sitl --lockstep-spin-us 0`, LockstepClient(spin=0))."""
    from bridge.link import LOCKSTEP_SPIN_S
    from bridge.lockstep import LockstepClient

    # A ground station that listens (never read here: the kernel drops what overflows its buffer). A closed
    # port would make the kernel answer each 50 Hz telemetry datagram with an ICMP port-unreachable.
    gcs = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    gcs.bind(("127.0.0.1", 0))
    cmd = [sys.executable, "-m", "quadsr.cli", "sitl", "--hil", "udp:127.0.0.1:0",
           "--gcs", f"udp:127.0.0.1:{gcs.getsockname()[1]}", "--status-interval", "0", *extra,
           *(() if spin else ("--lockstep-spin-us", "0"))]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        m = re.search(r"listening for the companion on (udp:[\d.]+:\d+)", line)
        if m is None:
            raise RuntimeError(f"unexpected SITL output: {line!r}")
        with LockstepClient(m.group(1), timeout=5.0, spin=LOCKSTEP_SPIN_S if spin else 0.0) as client:
            client.connect(10.0)
            throttles = (0.6, 0.6, 0.6, 0.6)
            for _ in range(200):  # warm up
                client.step(throttles)
            switches0 = _context_switches(proc.pid)
            sitl0, own0, t0 = _cpu_times(proc.pid), os.times(), time.perf_counter()
            for _ in range(steps):
                client.step(throttles)
            wall = time.perf_counter() - t0
            sitl1, own1 = _cpu_times(proc.pid), os.times()
            switches1 = _context_switches(proc.pid)
            us = 1e6 / steps
            return {
                "full": steps / wall,
                "sitl_cpu": (sum(sitl1) - sum(sitl0)) * us,
                "client_cpu": (own1.user + own1.system - own0.user - own0.system) * us,
                "sitl_sys": (sitl1[1] - sitl0[1]) * us,
                "client_sys": (own1.system - own0.system) * us,
                "sitl_vol": (switches1[0] - switches0[0]) / steps,
                "sitl_invol": (switches1[1] - switches0[1]) / steps,
            }
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
        gcs.close()


def main() -> int:
    """Run the three measurements --repeats times and print medians."""
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=20000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--echo", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--echo-spin", type=float, default=0.0, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.echo:
        echo_server(args.echo_spin)
        return 0
    full_kinds = ("full", "sitl_cpu", "client_cpu", "sitl_sys", "client_sys", "sitl_vol", "sitl_invol")
    kinds = ("physics", "physics_cpu", *full_kinds)
    names = ["ceiling", "ceiling_cpu", "ceiling_polled", "ceiling_polled_cpu"]
    names += [f"{k} {v}" for v in VEHICLES for k in kinds]
    names += [f"nospin_{k} {v}" for v in VEHICLES for k in ("full", "sitl_cpu", "client_cpu")]
    results: dict[str, list[float]] = {k: [] for k in names}
    for i in range(args.repeats):
        rate, cpu = ceiling_rate(args.steps)
        results["ceiling"].append(rate)
        results["ceiling_cpu"].append(cpu)
        rate, cpu = ceiling_rate(args.steps, LOCKSTEP_SPIN_S)
        results["ceiling_polled"].append(rate)
        results["ceiling_polled_cpu"].append(cpu)
        for v in VEHICLES:
            physics, physics_cpu = physics_rate(args.steps, v)
            results[f"physics {v}"].append(physics)
            results[f"physics_cpu {v}"].append(physics_cpu)
            extra = ("--vehicle", v) + (AERO_WIND_FLAGS if v == "fang-chen-aero" else ())
            for k, value in full_rate(args.steps, extra).items():
                results[f"{k} {v}"].append(value)
            nospin = full_rate(args.steps, extra, spin=False)
            for k in ("full", "sitl_cpu", "client_cpu"):
                results[f"nospin_{k} {v}"].append(nospin[k])
        print(f"run {i + 1}: " + ", ".join(f"{k} {v[-1]:,.2f}" if "vol" in k else f"{k} {v[-1]:,.0f}"
                                          for k, v in results.items()), flush=True)
    med = {k: statistics.median(v) for k, v in results.items()}
    from sitl import compiled_physics

    derivative = "compiled (sitl._derivative)" if compiled_physics.available() else "Python"
    print(f"cpu cores: {os.cpu_count()}, steps per run: {args.steps}, medians of {args.repeats} runs; "
          f"physics derivative: {derivative}")
    print(f"messaging ceiling (bare pymavlink ping-pong, 2 processes): {med['ceiling']:,.0f} round trips/s "
          f"({1e6 / med['ceiling']:.1f} us); CPU per round trip, both processes: {med['ceiling_cpu']:.0f} us")
    print(f"  the same, both polling for each datagram up to {LOCKSTEP_SPIN_S * 1e6:.0f} us before sleeping "
          f"(as the lockstep links): {med['ceiling_polled']:,.0f} round trips/s, CPU "
          f"{med['ceiling_polled_cpu']:.0f} us; the floor's ceiling is the faster of the two")
    ceiling = max(med["ceiling"], med["ceiling_polled"])
    ok = True
    for v in VEHICLES:
        physics, full = med[f"physics {v}"], med[f"full {v}"]
        ratio = full / ceiling
        print(f"{v}:")
        print(f"  physics alone (Quadrotor.step + SensorModel.sample): {physics:,.0f} steps/s "
              f"({1e6 / physics:.1f} us/step); by CPU time {med[f'physics_cpu {v}']:,.0f} steps/s")
        print(f"  full SITL in lockstep (LockstepClient, constant throttles): {full:,.0f} steps/s "
              f"({1e6 / full:.1f} us/step, {full * 0.004:.1f}x real time)")
        cpu = med[f"sitl_cpu {v}"] + med[f"client_cpu {v}"]
        print(f"  CPU per step: SITL process {med[f'sitl_cpu {v}']:.0f} us (physics, sensors, frames, UDP), "
              f"companion {med[f'client_cpu {v}']:.0f} us; both / the ceiling's: "
              f"{cpu / med['ceiling_cpu']:.2f}")
        print(f"  of which in the kernel (system time: UDP, wake-ups, context switches): SITL "
              f"{med[f'sitl_sys {v}']:.0f} us, companion {med[f'client_sys {v}']:.0f} us")
        print(f"  SITL context switches per step: {med[f'sitl_invol {v}']:.2f} involuntary (companion woken "
              f"on the SITL's core), {med[f'sitl_vol {v}']:.2f} voluntary (the SITL slept for the reply)")
        print(f"  the same without polling for the reply (both sleep at once): "
              f"{med[f'nospin_full {v}']:,.0f} "
              f"steps/s (SITL {med[f'nospin_sitl_cpu {v}']:.0f} us, companion "
              f"{med[f'nospin_client_cpu {v}']:.0f} us of CPU per step); polling / not: "
              f"{full / med[f'nospin_full {v}']:.2f}")
        print(f"  full / ceiling: {ratio:.2f}; physics share of a full step: {full / physics:.0%}")
        ok = ok and full >= 5000 and ratio >= 0.5 and physics >= 20000
    print(f"floors (each vehicle: physics >= 20,000 steps/s, full >= 5000 steps/s, full/ceiling >= 0.5): "
          f"{'PASS' if ok else 'FAIL'}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
