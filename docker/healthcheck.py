#!/usr/bin/env python3
"""Container health check for `quadsr sitl`: read the SITL's ground-link telemetry, never touch its HIL link.

The SITL sends PX4-like telemetry to its `--gcs` address (in the image: udp:127.0.0.1:14550). This script
binds that address for a few seconds and judges the SITL from what arrives:

- alive: HEARTBEATs from sysid 1 / compid 1 (a PX4 quadrotor) and LOCAL_POSITION_NED whose time_boot_ms
  advances between two reads. While no companion drives it that clock is the SITL's wall clock (its serving
  loop runs); once a companion steps it, it is the simulated clock (sim time moves).
- stepping: alive, and the HEARTBEAT's PX4 main mode is OFFBOARD, which the SITL reports only while a
  companion drives its lockstep (phase stepping).
- failsafe: the HEARTBEAT's system_status is MAV_STATE_CRITICAL (the companion stopped answering).

`--require ready` (the image's HEALTHCHECK) passes when the SITL is alive and not in failsafe: it is stepping,
or it is up and will step as soon as a companion connects. In lockstep sim time cannot move before a companion
does, so this is the gate a companion may wait on (`depends_on: condition: service_healthy`).
`--require stepping` passes only while sim time moves under a companion (for a check during a flight).

A check that finds the listen address taken (another check running: Docker's own beside a `docker exec` one)
waits for it up to --timeout s. Exit 0 healthy, 1 unhealthy (also when the address stays taken: Docker
reserves 2), 2 bad arguments; one line says why.
"""

from __future__ import annotations

import argparse
import errno
import socket
import sys
import time
from dataclasses import dataclass, field

from pymavlink.dialects.v20 import common as mavlink

DEFAULT_LISTEN = "udp:127.0.0.1:14550"
SITL_SYSTEM_ID = 1
SITL_COMPONENT_ID = 1
PX4_MAIN_MODE_OFFBOARD = 6  # PX4 custom_mode bits 16..23
HEALTHY, UNHEALTHY, USAGE = 0, 1, 2


@dataclass
class Observed:
    """What the ground link showed during one check."""

    heartbeat: object | None = None  # the last HEARTBEAT from the SITL
    clock_ms: list[int] = field(default_factory=list)  # LOCAL_POSITION_NED time_boot_ms since that HEARTBEAT
    messages: int = 0

    @property
    def advancing(self) -> bool:
        """Whether the SITL's clock moved between two reads after the last HEARTBEAT."""
        return len(self.clock_ms) >= 2 and self.clock_ms[-1] > self.clock_ms[0]

    @property
    def stepping(self) -> bool:
        """Whether the last HEARTBEAT says a companion drives the lockstep (PX4 OFFBOARD)."""
        hb = self.heartbeat
        return hb is not None and (hb.custom_mode >> 16) & 0xFF == PX4_MAIN_MODE_OFFBOARD

    @property
    def failsafe(self) -> bool:
        """Whether the last HEARTBEAT reports the failsafe (MAV_STATE_CRITICAL)."""
        return self.heartbeat is not None and self.heartbeat.system_status == mavlink.MAV_STATE_CRITICAL


def parse_listen(text: str) -> tuple[str, int]:
    """`udp:HOST:PORT` -> (host, port) to bind."""
    kind, _, rest = text.partition(":")
    host, _, port = rest.rpartition(":")
    if kind not in ("udp", "udpin") or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"bad listen address {text!r}: expected udp:HOST:PORT, e.g. {DEFAULT_LISTEN}")
    return host, int(port)


def bind(address: tuple[str, int], wait: float) -> socket.socket:
    """A UDP socket bound to address; while another check holds it, retry for up to wait s (wall)."""
    deadline = time.monotonic() + wait
    while True:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.bind(address)
            return sock
        except OSError as exc:
            sock.close()
            if exc.errno != errno.EADDRINUSE or time.monotonic() >= deadline:
                raise
        time.sleep(0.1)


def verdict(seen: Observed, require: str) -> tuple[int, str] | None:
    """(exit code, reason) once the observations decide the check, else None (keep listening)."""
    if seen.heartbeat is None or not seen.advancing:
        return None
    clock = f"clock {seen.clock_ms[-1] / 1000:.3f} s"
    if seen.failsafe:
        return UNHEALTHY, f"unhealthy: the SITL is in failsafe (no companion reply), {clock}"
    if seen.stepping:
        return HEALTHY, f"healthy: the SITL is stepping (a companion drives it), {clock} advancing (sim)"
    if require == "stepping":
        return UNHEALTHY, f"unhealthy: the SITL is not stepping (waiting for a companion), {clock} (wall)"
    return HEALTHY, f"healthy: the SITL is up and waiting for a companion, {clock} advancing (wall)"


def observe(sock: socket.socket, require: str, timeout: float) -> tuple[int, str]:
    """Read ground-link datagrams until a verdict or timeout s (wall); returns (exit code, reason)."""
    parser = mavlink.MAVLink(None)
    parser.robust_parsing = True
    seen = Observed()
    deadline = time.monotonic() + timeout
    while True:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            break
        sock.settimeout(remaining)
        try:
            data = sock.recv(65535)
        except TimeoutError:
            break
        except OSError:
            continue
        for msg in parser.parse_buffer(data) or []:
            if msg.get_srcSystem() != SITL_SYSTEM_ID or msg.get_srcComponent() != SITL_COMPONENT_ID:
                continue
            kind = msg.get_type()
            seen.messages += 1
            if kind == "HEARTBEAT" and msg.type == mavlink.MAV_TYPE_QUADROTOR:
                seen.heartbeat = msg
                seen.clock_ms = []
            elif kind == "LOCAL_POSITION_NED" and seen.heartbeat is not None:
                seen.clock_ms.append(msg.time_boot_ms)
        decided = verdict(seen, require)
        if decided is not None:
            return decided
    if seen.messages == 0:
        return UNHEALTHY, f"unhealthy: no telemetry from the SITL within {timeout:g} s (is it running?)"
    if seen.heartbeat is None:
        return UNHEALTHY, f"unhealthy: no HEARTBEAT from the SITL within {timeout:g} s"
    return UNHEALTHY, f"unhealthy: the SITL's clock did not advance within {timeout:g} s (stalled?)"


def build_parser() -> argparse.ArgumentParser:
    """The health check's command-line parser."""
    p = argparse.ArgumentParser(prog="healthcheck.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--listen", default=DEFAULT_LISTEN, metavar="udp:HOST:PORT",
                   help=f"the SITL's --gcs address, bound here (default {DEFAULT_LISTEN})")
    p.add_argument("--require", choices=("ready", "stepping"), default="ready",
                   help="ready: stepping, or up and waiting for a companion (default); "
                        "stepping: sim time moves under a companion")
    p.add_argument("--timeout", type=float, default=3.0, metavar="S",
                   help="wall seconds to listen before giving up (default 3; HEARTBEAT is 1 Hz)")
    return p


def main(argv: list[str] | None = None) -> int:
    """Run one check; exit code 0 healthy, 1 unhealthy, 2 bad arguments."""
    p = build_parser()
    args = p.parse_args(argv)
    if not args.timeout > 0:
        p.error(f"--timeout must be a positive number of seconds, got {args.timeout}")
    try:
        address = parse_listen(args.listen)
    except ValueError as exc:
        print(f"healthcheck: {exc}", file=sys.stderr)
        return USAGE
    try:
        sock = bind(address, args.timeout)
    except OSError as exc:
        print(f"healthcheck: cannot listen on {args.listen}: {exc.strerror} (another check running?)",
              file=sys.stderr)
        return UNHEALTHY
    try:
        code, reason = observe(sock, args.require, args.timeout)
    finally:
        sock.close()
    print(reason, flush=True)
    return code


if __name__ == "__main__":
    sys.exit(main())
