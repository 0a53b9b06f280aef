"""Local NED (m) <-> geodetic (lat, lon deg, alt m AMSL): the project's one geodesy, for every part.

LocalFrame: PX4's map projection, azimuthal equidistant on a sphere of radius 6371 km (PX4's MapProjection),
used by the SITL (HIL_GPS, ground link) and the companion's estimator: to_geodetic and to_ned are exact
inverses of each other, so a round trip is limited by float rounding only (micrometres). Altitude is
home.alt - down.
flat_earth_ned: ArduPilot's flat-earth Location distances (its LOCATION_SCALING_FACTOR), for positions in
ArduPilot logs.
"""

from __future__ import annotations

import math
from typing import Protocol

import numpy as np

EARTH_RADIUS = 6371000.0  # m, as PX4's CONSTANTS_RADIUS_OF_EARTH
# m: ArduPilot's LOCATION_SCALING_FACTOR (0.011131884502145034 m per 1e-7 deg) as a radius
ARDUPILOT_EARTH_RADIUS = 0.011131884502145034 * 1e7 * 180.0 / math.pi


class _GeoPoint(Protocol):
    lat: float
    lon: float
    alt: float


class LocalFrame:
    """A NED frame tangent at a home point (lat, lon deg; alt m AMSL)."""

    def __init__(self, lat: float, lon: float, alt: float):
        self.lat = lat
        self.lon = lon
        self.alt = alt
        self._lat0 = math.radians(lat)
        self._lon0 = math.radians(lon)
        self._sin0 = math.sin(self._lat0)
        self._cos0 = math.cos(self._lat0)

    @classmethod
    def at(cls, home: _GeoPoint) -> LocalFrame:
        """The frame at a home point with .lat, .lon (deg) and .alt (m), e.g. a vehicle's HomeConfig."""
        return cls(home.lat, home.lon, home.alt)

    def to_geodetic(self, north: float, east: float, down: float) -> tuple[float, float, float]:
        """(lat deg, lon deg, alt m AMSL) of a NED position (m)."""
        x = north / EARTH_RADIUS
        y = east / EARTH_RADIUS
        c = math.sqrt(x * x + y * y)
        if c == 0.0:
            return self.lat, self.lon, self.alt - down
        sin_c = math.sin(c)
        cos_c = math.cos(c)
        lat = math.asin(cos_c * self._sin0 + x * sin_c * self._cos0 / c)
        lon = self._lon0 + math.atan2(y * sin_c, c * self._cos0 * cos_c - x * self._sin0 * sin_c)
        return math.degrees(lat), math.degrees(lon), self.alt - down

    def to_ned(self, lat: float, lon: float, alt: float) -> tuple[float, float, float]:
        """NED position (m) of a geodetic point (lat, lon deg; alt m AMSL)."""
        la = math.radians(lat)
        d_lon = math.radians(lon) - self._lon0
        sin_lat = math.sin(la)
        cos_lat = math.cos(la)
        cos_d = math.cos(d_lon)
        arg = max(-1.0, min(1.0, self._sin0 * sin_lat + self._cos0 * cos_lat * cos_d))
        c = math.acos(arg)
        # c/sin(c) -> 1 + c^2/6: insensitive to acos's rounding near c = 0.
        k = 1.0 if c < 1e-9 else c / math.sin(c)
        north = k * (self._cos0 * sin_lat - self._sin0 * cos_lat * cos_d) * EARTH_RADIUS
        east = k * cos_lat * math.sin(d_lon) * EARTH_RADIUS
        return north, east, self.alt - alt


def ned_to_geodetic(north: float, east: float, down: float, home: _GeoPoint) -> tuple[float, float, float]:
    """(lat deg, lon deg, alt m AMSL) of a NED position (m) about home."""
    return LocalFrame.at(home).to_geodetic(north, east, down)


def geodetic_to_ned(lat: float, lon: float, alt: float, home: _GeoPoint) -> tuple[float, float, float]:
    """NED position (m) about home of a geodetic point (lat, lon deg; alt m AMSL)."""
    return LocalFrame.at(home).to_ned(lat, lon, alt)


def flat_earth_ned(lat: np.ndarray, lon: np.ndarray, alt: np.ndarray) -> np.ndarray:
    """(N, 3) NED m of geodetic points (deg, deg, m AMSL) from the first one, as ArduPilot's Location does.

    North = d_lat * R, east = d_lon * R * cos(mean latitude of the two points) with ArduPilot's radius.
    """
    lat, lon, alt = (np.asarray(a, dtype=float) for a in (lat, lon, alt))
    north = np.radians(lat - lat[0]) * ARDUPILOT_EARTH_RADIUS
    east = np.radians(lon - lon[0]) * ARDUPILOT_EARTH_RADIUS * np.cos(np.radians((lat + lat[0]) / 2.0))
    return np.column_stack((north, east, -(alt - alt[0])))
