"""Earth models: Earth rotation rate and field references in local-level frames.

Frames: NED (north, east, down) is the frame of the papers' simulations; ENU is BROAD's and VQF's. Convert
with :func:`ned_to_enu` at the edges, never by guessing.
"""

from __future__ import annotations

import jax.numpy as jnp

__all__ = ["EARTH_RATE", "GRAVITY", "earth_rate_ned", "ned_to_enu", "LISBON_LATITUDE_DEG", "LISBON_FIELD_NED_NT"]

#: Norm of the Earth's rotation rate (rad/s), WGS-84 (batista2019-ges Section IV).
EARTH_RATE = 7.2921150e-5
#: Standard gravity (m/s^2).
GRAVITY = 9.80665

#: Latitude of the Batista et al. simulations (deg, north), Section IV of both papers.
LISBON_LATITUDE_DEG = 38.7138
#: Magnetic field (nT, NED) of IGRF-11 at 38.7138 N, 9.1394 W, sea level, as used in batista2019-so3
#: Section 4 (I_m ~ [2.6338, 0.0851, 3.6359] x 1e4 nT); the GES paper uses the same IGRF-11 point.
LISBON_FIELD_NED_NT = (2.6338e4, 0.0851e4, 3.6359e4)


def earth_rate_ned(latitude_deg, rate: float = EARTH_RATE, dtype=None):
    """Earth rotation rate in NED at a geodetic latitude (deg): rate * [cos(lat), 0, -sin(lat)] (rad/s)."""
    lat = jnp.deg2rad(jnp.asarray(latitude_deg, dtype=dtype))
    return rate * jnp.stack([jnp.cos(lat), jnp.zeros_like(lat), -jnp.sin(lat)], axis=-1)


def ned_to_enu(v):
    """Re-express a vector given in NED coordinates in ENU coordinates (x_E, y_N, z_U)."""
    v = jnp.asarray(v)
    return jnp.stack([v[..., 1], v[..., 0], -v[..., 2]], axis=-1)
