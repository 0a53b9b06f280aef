"""Shutdown: repeated SIGTERM/SIGINT never kill a process half-way; children die with their parent."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

from conftest import REPO


def _alive(pid: int) -> bool:
    """Whether pid runs (a zombie waiting for its reaper counts as dead)."""
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def _signal_storm(proc: subprocess.Popen, signals: tuple[int, ...]) -> int:
    """Send signals to proc back to back, one after another, until it exits; return its exit code."""
    k = 0
    while proc.poll() is None and k < 20000:
        try:
            proc.send_signal(signals[k % len(signals)])
        except ProcessLookupError:
            break
        k += 1
        time.sleep(0.001)
    return proc.wait(20)


def test_sitl_exits_0_under_a_storm_of_sigterm_and_sigint(start_sitl):
    """Issue 16 item 4: a 2nd SIGTERM during shutdown killed the SITL (-15); now later ones are absorbed."""
    sitl = start_sitl("--no-gcs")
    code = _signal_storm(sitl.proc, (signal.SIGTERM, signal.SIGTERM, signal.SIGINT))
    sitl._reader.join(5.0)
    assert code == 0, sitl.output
    assert "(exit)" in sitl.output


def test_stop_signals_absorbs_repeats_and_keeps_its_handler_after_a_stop():
    from bridge.shutdown import StopSignals

    stops = []
    before = signal.getsignal(signal.SIGTERM)
    with StopSignals(on_stop=lambda: stops.append(1)) as s:
        for _ in range(5):
            os.kill(os.getpid(), signal.SIGTERM)
            os.kill(os.getpid(), signal.SIGINT)
    assert s.requested and s.signum == signal.SIGTERM and s.exit_code == 143 and stops == [1]
    assert signal.getsignal(signal.SIGTERM) == signal.SIG_IGN  # not the default: a late signal stays harmless
    os.kill(os.getpid(), signal.SIGTERM)
    signal.signal(signal.SIGTERM, before)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    with StopSignals(raise_interrupt=True) as quiet:
        pass
    assert not quiet.requested and signal.getsignal(signal.SIGTERM) == before  # no signal: restored


def test_sitl_child_dies_when_its_parent_is_killed_with_sigkill(tmp_path):
    """Issue 16 item 5: a `quadsr paper` killed outright left its SITL child running."""
    script = textwrap.dedent("""
        import sys, time
        from quadsr.sitl_process import SitlProcess
        sitl = SitlProcess().start()
        print(sitl.proc.pid, flush=True)
        time.sleep(600)
    """)
    parent = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True, cwd=REPO)
    try:
        child = int(parent.stdout.readline())
        assert _alive(child)
        parent.kill()
        parent.wait(10)
        deadline = time.monotonic() + 20
        while _alive(child) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not _alive(child), "the SITL child outlived its SIGKILLed parent"
    finally:
        parent.kill()
        parent.wait()


def test_sitl_child_last_lines_reach_its_log_when_its_parent_exits_after_stop(tmp_path):
    """The SITL's output went to its log through a daemon thread that a parent exiting right after stop()
    cut off: the log could lack the SITL's last lines."""
    script = textwrap.dedent("""
        import sys
        from quadsr.sitl_process import SitlProcess
        sitl = SitlProcess(["--sensors", "ideal"], log_path=sys.argv[1]).start()
        sys.exit(sitl.stop())
    """)
    log = tmp_path / "sitl.log"
    done = subprocess.run([sys.executable, "-c", script, str(log)], cwd=REPO, timeout=60)
    assert done.returncode == 0
    lines = log.read_text().splitlines()
    assert lines and lines[-1].endswith("(exit)"), lines[-3:]


def test_fly_writes_steps_and_metrics_on_sigterm_as_on_sigint(start_sitl, tmp_path):
    """Issue 16 item 6: `quadsr fly` on SIGTERM exited 143 without steps.csv or the metrics."""
    sitl = start_sitl("--no-gcs", "--sensors", "ideal", "--lockstep-timeout", "20")
    out = tmp_path / "flight"
    proc = subprocess.Popen(
        [sys.executable, "-m", "quadsr.cli", "fly", "--no-progress", "--controller", "pid", "--trajectory",
         "case1", "--duration", "600", "--hil", sitl.hil, "--out", str(out), "--link-timeout", "10"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO,
    )
    try:
        deadline = time.monotonic() + 60
        tlog = out / "flight.tlog"
        while (not tlog.exists() or tlog.stat().st_size < 20000) and proc.poll() is None:
            assert time.monotonic() < deadline, "the flight did not start"
            time.sleep(0.05)
        code = _signal_storm(proc, (signal.SIGTERM,))
        stdout, stderr = proc.communicate(10)
    finally:
        proc.kill()
        proc.wait()
    assert code == 143, stdout + stderr
    assert "interrupted (SIGTERM)" in stderr and "Traceback" not in stderr
    assert len((out / "steps.csv").read_text().splitlines()) > 10
    for name in ("metrics.md", "metrics.csv"):
        assert (out / name).stat().st_size > 0, name
