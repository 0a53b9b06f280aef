"""The README's first job: `quadsr hover-check` flies and passes, over real UDP."""

import subprocess
import sys


def test_hover_check_passes(tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "quadsr.cli", "hover-check", "--duration", "6", "--out", str(tmp_path)],
        capture_output=True, text=True, timeout=120,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    assert "hover check: PASS" in result.stdout
    assert (tmp_path / "hover.tlog").stat().st_size > 10_000


def test_hover_check_rejects_bad_altitude():
    result = subprocess.run([sys.executable, "-m", "quadsr.cli", "hover-check", "--altitude", "-3"],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2
    assert "--altitude" in result.stderr and "Traceback" not in result.stderr
