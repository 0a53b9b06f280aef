"""bridge.geodesy, the one geodesy: ArduPilot's flat earth here (PX4's projection: test_sensors)."""

from __future__ import annotations

import numpy as np
import pytest

from bridge.geodesy import LocalFrame, flat_earth_ned


def test_flat_earth_uses_ardupilots_location_scaling():
    lat0, lon0 = 47.3977420, 8.5455940
    lat = np.array([lat0, lat0 + 1e-5, lat0, lat0 + 1e-3])
    lon = np.array([lon0, lon0, lon0 + 1e-5, lon0 + 1e-3])
    alt = np.array([488.0, 490.0, 487.5, 500.0])
    ned = flat_earth_ned(lat, lon, alt)
    factor = 0.011131884502145034  # m per 1e-7 deg (ArduPilot's LOCATION_SCALING_FACTOR)
    assert ned[0] == pytest.approx([0.0, 0.0, 0.0])
    assert ned[1] == pytest.approx([100 * factor, 0.0, -2.0], rel=1e-8)  # lat0 + 1e-5 - lat0 is 1e-5 to 1e-10
    assert ned[2] == pytest.approx([0.0, 100 * factor * np.cos(np.radians(lat0)), 0.5], rel=1e-9)
    # within a kilometre it agrees with PX4's projection to 0.2 % (the two Earth radii differ by 0.11 %)
    px4 = LocalFrame(lat0, lon0, 488.0)
    assert ned[3] == pytest.approx(px4.to_ned(lat[3], lon[3], alt[3]), rel=2e-3)
