"""ArduPilot instances are held while in use: parallel ArduPilotProcess users (tests on two workers, bench
runs) never pick the same instance between choosing it and ArduCopter binding its ports."""

from __future__ import annotations

import pytest

from quadsr.ardupilot_process import claim_free_instance
from quadsr.instance_lock import hold


def test_a_held_ardupilot_instance_is_not_picked_again_until_released():
    n, lock = claim_free_instance(240, 250)
    try:
        assert 240 <= n < 250
        assert hold("ardupilot", n) is None  # another claimant is refused
        with pytest.raises(RuntimeError, match="no free ArduPilot instance"):
            claim_free_instance(n, n + 1)
        other, other_lock = claim_free_instance(240, 250)
        assert other != n
        other_lock.close()
    finally:
        lock.close()
    again, lock = claim_free_instance(n, n + 1)  # released: free again
    assert again == n
    lock.close()


def test_px4_and_ardupilot_numbers_are_held_apart():
    px4 = hold("px4", 245)
    assert px4 is not None
    try:
        ardupilot = hold("ardupilot", 245)  # different simulators, different ports: both may hold 245
        assert ardupilot is not None
        ardupilot.close()
    finally:
        px4.close()
