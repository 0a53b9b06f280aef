"""PX4 SITL from a PX4 build, flying quadsr's SITL: the work folder, the ports, and the PX4 child process.

A PX4 build is a folder with `bin/px4` and `etc/` (PX4's ROMFS), such as `../shared/px4` or a user's
`build/px4_sitl_default`. Each run gets a work folder: `bin/` (links px4-<command> -> px4, as a PX4 build
has them; a copied build may hold them as plain files naming their target), `etc/` (a copy of the build's
ROMFS with quadsr's airframe added to `init.d-posix/airframes`) and `rootfs/` (PX4's working directory:
parameters, dataman, ULogs under `rootfs/log/`).
"""

from __future__ import annotations

import os
import shutil
import socket
from dataclasses import dataclass
from pathlib import Path
from typing import IO

from bridge.errors import UserError
from quadsr.child_process import OutputProcess
from quadsr.instance_lock import hold
from quadsr.px4_airframe import AIRFRAME_ID, Px4Airframe


@dataclass(frozen=True)
class Px4Ports:
    """The ports of PX4 SITL instance N (127.0.0.1), as PX4's init scripts set them."""

    instance: int

    @property
    def simulator(self) -> int:
        """TCP port PX4 connects to for the simulator (quadsr sitl listens): 4560+N."""
        return 4560 + self.instance

    @property
    def gcs(self) -> int:
        """PX4's GCS link, local UDP port 18570+N (it sends to 14550 until a client speaks)."""
        return 18570 + self.instance

    @property
    def offboard(self) -> int:
        """PX4's offboard API link, local UDP port 14580+N."""
        return 14580 + self.instance

    @property
    def offboard_remote(self) -> int:
        """Where PX4's offboard link sends (MAVSDK's udpin port): 14540+N, 14549 for N > 9."""
        return 14540 + self.instance if self.instance <= 9 else 14549

    @property
    def udp_local(self) -> tuple[int, ...]:
        """Every UDP port PX4 binds (GCS, offboard, onboard payload, gimbal), and for N <= 9 the offboard
        companion's 14540+N (bridge.offboard.default_local)."""
        n = self.instance
        return (18570 + n, 14580 + n, 14280 + n, 13030 + n) + ((14540 + n,) if n <= 9 else ())

    def system_id(self) -> int:
        """PX4's MAV_SYS_ID for this instance: N+1."""
        return self.instance + 1


def ports_free(ports: Px4Ports) -> bool:
    """True if the simulator TCP port and every UDP port of the instance can be bound right now."""
    socks = []
    try:
        wanted = [(socket.SOCK_STREAM, ports.simulator)] + [(socket.SOCK_DGRAM, p) for p in ports.udp_local]
        for kind, port in wanted:
            s = socket.socket(socket.AF_INET, kind)
            socks.append(s)
            s.bind(("127.0.0.1", port))
        return True
    except OSError:
        return False
    finally:
        for s in socks:
            s.close()


def claim_instance(n: int) -> IO[bytes] | None:
    """Hold PX4 instance n for this process (quadsr.instance_lock); None when another process holds it."""
    return hold("px4", n)


def claim_free_instance(first: int, last: int) -> tuple[int, IO[bytes]]:
    """The first PX4 instance in [first, last] nobody holds and whose ports are free, and its held lock: two
    `quadsr px4` started at once never take the same one (UserError if none is free)."""
    for n in range(first, last + 1):
        lock = claim_instance(n)
        if lock is None:
            continue
        if ports_free(Px4Ports(n)):
            return n, lock
        lock.close()
    raise UserError(f"no PX4 instance in {first}..{last} has free ports", hint="stop other PX4 or simulators")


def check_build(path: Path) -> Path:
    """The absolute PX4 build folder (UserError naming what is missing)."""
    root = Path(path).expanduser().resolve()
    px4 = root / "bin" / "px4"
    rcs = root / "etc" / "init.d-posix" / "rcS"
    if not px4.is_file() or not os.access(px4, os.X_OK):
        raise UserError(f"--px4 {path}: no executable bin/px4 in it",
                        hint="give a PX4 SITL build folder (bin/px4 and etc/), e.g. ../shared/px4 or "
                             "PX4-Autopilot/build/px4_sitl_default")
    if not rcs.is_file():
        raise UserError(f"--px4 {path}: no etc/init.d-posix/rcS in it", hint="is it a px4_sitl build?")
    return root


@dataclass(frozen=True)
class Px4Tree:
    """A prepared work folder: the px4 binary to run, the ROMFS copy, PX4's working dir, the model name."""

    px4: Path
    etc: Path
    rootfs: Path
    model: str


def prepare_work(build: Path, work: Path, airframe: Px4Airframe, source: str) -> Px4Tree:
    """Fill `work` with bin/ (command links), etc/ (ROMFS copy + the airframe) and rootfs/ (fresh)."""
    work = work.resolve()
    try:
        for name in ("bin", "etc", "rootfs"):
            if (work / name).exists():
                shutil.rmtree(work / name)
        bin_dir = work / "bin"
        bin_dir.mkdir(parents=True)
        (bin_dir / "px4").symlink_to(build / "bin" / "px4")
        for entry in (build / "bin").iterdir():
            if not entry.name.startswith("px4-"):
                continue
            if entry.name.endswith(".sh"):
                (bin_dir / entry.name).symlink_to(entry)
            else:
                (bin_dir / entry.name).symlink_to("px4")
        etc = work / "etc"
        shutil.copytree(build / "etc", etc)
        for path in [etc, *etc.rglob("*")]:  # a read-only build gives read-only copies
            path.chmod(path.stat().st_mode | 0o200)
        airframes = etc / "init.d-posix" / "airframes"
        (airframes / airframe.file_name(AIRFRAME_ID)).write_text(airframe.text(source))
        rootfs = work / "rootfs"
        rootfs.mkdir()
    except OSError as exc:
        raise UserError(f"cannot prepare the PX4 work folder {work}: {exc}",
                        hint="give a writable folder with --work") from None
    return Px4Tree(bin_dir / "px4", etc, rootfs, airframe.model_name())


class Px4Process(OutputProcess):
    """PX4 SITL as a child process (killed if this process dies), its output kept and echoed to a log."""

    def __init__(self, tree: Px4Tree, instance: int, log_path: Path):
        self.tree = tree
        self.instance = instance
        env = dict(os.environ, PX4_SIM_MODEL=tree.model)
        env["PATH"] = f"{tree.px4.parent}{os.pathsep}{env.get('PATH', '')}"
        args = [str(tree.px4), "-d", "-i", str(instance), "-w", str(tree.rootfs), str(tree.etc)]
        super().__init__(args, cwd=tree.rootfs, env=env, log_path=log_path)

    def ulogs(self) -> list[Path]:
        """The ULogs PX4 wrote so far, oldest first."""
        return sorted((self.tree.rootfs / "log").rglob("*.ulg"))
