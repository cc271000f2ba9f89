"""UTM coordinates (WGS84, northern hemisphere) of latitudes and longitudes and back: the
Krueger series to n^3, sub-millimetre within a zone. Maps with only ``lat`` / ``lon`` nodes
are placed in a recording's local frame with it (:mod:`scenarios.exid`, "Maps")."""

from __future__ import annotations

import math

import numpy as np

_A, _F = 6378137.0, 1 / 298.257223563
_N = _F / (2 - _F)
_AA = _A / (1 + _N) * (1 + _N**2 / 4 + _N**4 / 64)
_ALPHA = (
    _N / 2 - 2 * _N**2 / 3 + 5 * _N**3 / 16,
    13 * _N**2 / 48 - 3 * _N**3 / 5,
    61 * _N**3 / 240,
)
_BETA = (_N / 2 - 2 * _N**2 / 3 + 37 * _N**3 / 96, _N**2 / 48 + _N**3 / 15, 17 * _N**3 / 480)
_DELTA = (2 * _N - 2 * _N**2 / 3 - 2 * _N**3, 7 * _N**2 / 3 - 8 * _N**3 / 5, 56 * _N**3 / 15)
_E = 2 * math.sqrt(_N) / (1 + _N)
_K0, _E0 = 0.9996, 500000.0


def utm_zone(lon: float) -> int:
    """UTM zone (1..60) of a longitude in degrees."""
    return int((lon + 180.0) // 6.0) % 60 + 1


def utm_from_latlon(lat, lon, zone: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """UTM easting and northing (m, northern hemisphere) of WGS84 ``lat, lon`` (deg)."""
    lat, lon = np.asarray(lat, dtype=float), np.asarray(lon, dtype=float)
    z = utm_zone(float(np.mean(lon))) if zone is None else int(zone)
    phi, lam = np.radians(lat), np.radians(lon - (6 * z - 183))
    t = np.sinh(np.arctanh(np.sin(phi)) - _E * np.arctanh(_E * np.sin(phi)))
    xi = np.arctan2(t, np.cos(lam))
    eta = np.arctanh(np.sin(lam) / np.sqrt(1 + t**2))
    E = eta + sum(a * np.cos(2 * j * xi) * np.sinh(2 * j * eta) for j, a in enumerate(_ALPHA, 1))
    N = xi + sum(a * np.sin(2 * j * xi) * np.cosh(2 * j * eta) for j, a in enumerate(_ALPHA, 1))
    return _E0 + _K0 * _AA * E, _K0 * _AA * N


def latlon_from_utm(easting, northing, zone: int) -> tuple[np.ndarray, np.ndarray]:
    """WGS84 ``lat, lon`` (deg) of UTM coordinates (northern hemisphere) in ``zone``."""
    xi = np.asarray(northing, dtype=float) / (_K0 * _AA)
    eta = (np.asarray(easting, dtype=float) - _E0) / (_K0 * _AA)
    xi_ = xi - sum(b * np.sin(2 * j * xi) * np.cosh(2 * j * eta) for j, b in enumerate(_BETA, 1))
    eta_ = eta - sum(b * np.cos(2 * j * xi) * np.sinh(2 * j * eta) for j, b in enumerate(_BETA, 1))
    chi = np.arcsin(np.sin(xi_) / np.cosh(eta_))
    phi = chi + sum(d * np.sin(2 * j * chi) for j, d in enumerate(_DELTA, 1))
    lam = np.arctan2(np.sinh(eta_), np.cos(xi_))
    return np.degrees(phi), np.degrees(lam) + (6 * zone - 183)
