"""A newcomer's walk through README.md's CLI section: every example, in order, from an empty folder.

Each `quadsr sitl` line replaces the running SITL by a fresh one (as the README says to do), run in the
background on free ports; every other line runs to its end and must exit 0 without a traceback. Fast
settings only shorten flights (--duration) and give free ports (--hil, --gcs, --offboard); `quadsr paper`
(minutes, and tested end to end by test_paper_e2e.py) is only parsed.
"""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import free_udp_port

REPO = Path(__file__).resolve().parent.parent
pytestmark = pytest.mark.e2e
LISTENING = re.compile(r"listening for the companion on (udp:[\d.]+:\d+)")
FAST = {  # shorter flights; everything else as written
    ("excite", "paper-train"): ["--duration", "8"],
    ("excite", "paper-validate"): ["--duration", "4"],
    ("excite", "closed-loop"): ["--duration", "6"],
    ("fly", ""): ["--duration", "3"],
    ("hover-check", ""): ["--duration", "5"],  # its shortest
}


def readme_cli_commands() -> list[list[str]]:
    """The `quadsr ...` lines of the README's CLI section, comments stripped, in order."""
    text = (REPO / "README.md").read_text(encoding="utf-8")
    block = re.search(r"^## CLI\n.*?```bash\n(.*?)```", text, re.S | re.M).group(1)
    return [shlex.split(line, comments=True) for line in block.splitlines() if line.startswith("quadsr ")]


def _fast_flags(argv: list[str]) -> list[str]:
    profile = argv[argv.index("--profile") + 1] if "--profile" in argv else ""
    return FAST.get((argv[1], profile), [])


class Sitl:
    """A README `quadsr sitl` line running in the background in the walk's folder, on free ports."""

    def __init__(self, argv: list[str], cwd: Path, env: dict[str, str]):
        args = argv[2:] + ["--hil", "udp:127.0.0.1:0", "--status-interval", "0"]
        if "--offboard" in args:
            args[args.index("--offboard") + 1] = f"udp:127.0.0.1:{free_udp_port()}"
        args += ["--gcs", f"udp:127.0.0.1:{free_udp_port()}"]
        self.proc = subprocess.Popen([sys.executable, "-m", "quadsr.cli", "sitl", *args], cwd=cwd, env=env,
                                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        line = self.proc.stdout.readline()
        match = LISTENING.search(line)
        assert match, f"quadsr sitl {' '.join(args)}: {line}{self.proc.stdout.read() if not line else ''}"
        self.hil = match.group(1)

    def stop(self) -> None:
        self.proc.terminate()
        assert self.proc.wait(20) == 0


def test_the_readme_cli_section_works_in_order(tmp_path):
    from quadsr.cli import build_parser

    commands = readme_cli_commands()
    assert [c[1] for c in commands].count("sitl") >= 4 and commands[-1][1] == "hover-check"
    env = {**os.environ, "PYTHONPATH": str(REPO), "PYTHONUNBUFFERED": "1"}
    parser = build_parser()
    sitl: Sitl | None = None
    walked = []
    try:
        for argv in commands:
            parser.parse_args(argv[1:])  # every example's flags exist
            if argv[1] == "paper":
                continue
            if argv[1] == "sitl":
                if sitl is not None:
                    sitl.stop()
                sitl = Sitl(argv, tmp_path, env)
                continue
            args = argv[1:] + _fast_flags(argv)
            if argv[1] in ("excite", "fly"):
                args += ["--hil", sitl.hil]
            start = time.monotonic()
            done = subprocess.run([sys.executable, "-m", "quadsr.cli", *args], cwd=tmp_path, env=env,
                                  capture_output=True, text=True, timeout=240)
            walked.append((" ".join(argv), round(time.monotonic() - start, 1)))
            assert done.returncode == 0, f"{' '.join(argv)}:\n{done.stdout}\n{done.stderr}"
            assert "Traceback" not in done.stderr
            if argv[1] == "fly":  # stderr is a pipe here: no progress bar drawn into it
                assert "step/s" not in done.stderr and "%|" not in done.stderr, done.stderr
    finally:
        if sitl is not None:
            sitl.stop()
    print(walked)
    for name in ("train.tlog", "validate.tlog", "closed.tlog", "model.yaml", "true.yaml", "sitl.tlog",
                 "flights/case1/metrics.csv", "flights/case2/metrics.csv"):
        assert (tmp_path / name).stat().st_size > 0, name
    assert any((tmp_path / "validation").iterdir())


def test_hover_check_help_shows_the_defaults():
    done = subprocess.run([sys.executable, "-m", "quadsr.cli", "hover-check", "--help"], capture_output=True,
                          text=True, cwd=REPO, timeout=60)
    assert "(default: 2.0)" in done.stdout and "(default: fang-chen-buaa)" in done.stdout
