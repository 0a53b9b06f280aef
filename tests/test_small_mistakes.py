"""Issue 16 item 7: small mistakes get the right message; `quadsr --version` imports no subcommand."""

from __future__ import annotations

import socket
import subprocess
import sys

import pytest

from bridge.errors import UserError
from bridge.link import UdpLink, parse_endpoint
from quadsr.cli import main

HEAVY = ("numpy", "sympy", "scipy", "identification", "controller", "sitl", "pymavlink", "bridge", "argparse")


def test_version_answers_without_importing_any_subcommand():
    code = ("import sys; from quadsr.cli import main; assert main(['--version']) == 0; "
            f"print(sorted(m for m in sys.modules if m.split('.')[0] in {HEAVY!r}))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines() == ["quadsr 0.1.0", "[]"]


def test_a_directory_as_vehicle_is_named_a_directory(tmp_path, capsys):
    assert main(["model-from-vehicle", "--vehicle", str(tmp_path), "-o", str(tmp_path / "m.yaml")]) == 2
    err = capsys.readouterr().err
    assert "is a directory, not a file" in err and "not found" not in err and "Traceback" not in err


def test_bind_failures_get_the_hint_of_their_cause():
    with pytest.raises(UserError) as foreign:  # TEST-NET-1: never an address of this machine
        UdpLink(local=parse_endpoint("udp:192.0.2.10:4560"))
    hint = foreign.value.hint
    assert "not an address of this machine" in hint and "another process" not in hint
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind(("127.0.0.1", 0))
        port = taken.getsockname()[1]
        with pytest.raises(UserError) as busy:
            UdpLink(local=parse_endpoint(f"udp:127.0.0.1:{port}"))
    assert "another process" in busy.value.hint and f"udp:127.0.0.1:{port}" in str(busy.value)
