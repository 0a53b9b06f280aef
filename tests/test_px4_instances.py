"""PX4 instances are held while in use: parallel `quadsr px4` runs (and parallel test sessions) never pick
the same instance between choosing it and binding its ports."""

from __future__ import annotations

import subprocess
import sys

from conftest import REPO

from quadsr.cli import main
from quadsr.px4_launch import claim_free_instance, claim_instance


def test_a_held_instance_is_skipped_until_released():
    first, lock_a = claim_free_instance(185, 195)
    try:
        second, lock_b = claim_free_instance(185, 195)
        assert second > first  # the held one is not handed out again
        assert claim_instance(first) is None and claim_instance(second) is None
        lock_b.close()
        again = claim_instance(second)
        assert again is not None
        again.close()
    finally:
        lock_a.close()


def test_an_instance_held_by_another_process_is_skipped():
    first, lock = claim_free_instance(185, 195)
    lock.close()
    code = ("import sys, time; from quadsr.px4_launch import claim_instance; "
            f"lock = claim_instance({first}); print(lock is not None, flush=True); sys.stdin.read()")
    child = subprocess.Popen([sys.executable, "-c", code], cwd=REPO, stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline().strip() == "True"  # the child holds it now
        n, mine = claim_free_instance(first, 195)
        assert n != first
        mine.close()
    finally:
        child.communicate("", timeout=30)
    again = claim_instance(first)  # released with the child
    assert again is not None
    again.close()


def test_bad_instance_ranges_are_user_errors(capsys):
    for bad in ("9-1", "x", "1-2-3", "201"):
        assert main(["px4", "--instance", bad]) == 2
        err = capsys.readouterr().err
        assert "--instance" in err and "Traceback" not in err, err


def test_bad_paces_are_user_errors(capsys):
    for flags, said in ((["--max-rtf", "0"], "--max-rtf must be a positive number"),
                        (["--max-rtf", "nan"], "--max-rtf must be a positive number"),
                        (["--max-rtf", "2", "--mode", "realtime"], "both set the pace")):
        assert main(["px4", *flags]) == 2
        err = capsys.readouterr().err
        assert said in err and "Traceback" not in err, err
