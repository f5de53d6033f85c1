"""Light sets the tests share: directions from angles, and random domes."""
import numpy as np


def lights_at(elevations_deg, azimuths_deg) -> np.ndarray:
    """Unit directions at the given elevations above the horizon and azimuths (degrees)."""
    el, az = np.radians(elevations_deg), np.radians(azimuths_deg)
    return np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


def dome(n, seed=0, min_el=10) -> np.ndarray:
    """``n`` random lights between ``min_el`` and 88 degrees of elevation."""
    rng = np.random.default_rng(seed)
    return lights_at(rng.uniform(min_el, 88, n), rng.uniform(0, 360, n))
