"""Noll-indexed, Noll-normalised Zernike polynomials and Noll's coefficient covariance."""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
from scipy.special import gamma


def noll_to_nm(j: int) -> tuple[int, int]:
    """Noll index j >= 1 → (radial order n, azimuthal frequency m >= 0)."""
    if j < 1:
        raise ValueError(f"Noll index must be >= 1, got {j}")
    n = int((math.isqrt(8 * j - 7) - 1) // 2)
    p = j - n * (n + 1) // 2  # 1-based position within order n
    m = 2 * (p // 2) if n % 2 == 0 else 2 * ((p + 1) // 2) - 1
    return n, m


def radial(n: int, m: int, rho: np.ndarray) -> np.ndarray:
    out = np.zeros_like(rho, dtype=np.float64)
    for k in range((n - m) // 2 + 1):
        c = (
            (-1) ** k
            * math.factorial(n - k)
            / (math.factorial(k) * math.factorial((n + m) // 2 - k) * math.factorial((n - m) // 2 - k))
        )
        out += c * rho ** (n - 2 * k)
    return out


def zernike(j: int, rho: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Z_j(ρ, θ), orthonormal over the unit disk: (1/π)∫ Z_j Z_j' = δ_jj'. Z2 = 2ρcosθ, Z3 = 2ρsinθ."""
    n, m = noll_to_nm(j)
    r = radial(n, m, np.asarray(rho, dtype=np.float64))
    if m == 0:
        return math.sqrt(n + 1) * r
    ang = np.cos(m * theta) if j % 2 == 0 else np.sin(m * theta)
    return math.sqrt(2 * (n + 1)) * r * ang


@lru_cache(maxsize=16)
def noll_covariance(n_modes: int) -> np.ndarray:
    """Covariance of a_2..a_J (J = n_modes) in rad² for D/r0 = 1 (Noll 1976; multiply by (D/r0)^(5/3)).

    Returned read-only, shape (J-1, J-1); index i corresponds to Noll j = i + 2.
    """
    js = range(2, n_modes + 1)
    C = np.zeros((n_modes - 1, n_modes - 1))
    for a, j in enumerate(js):
        n, m = noll_to_nm(j)
        for b, jp in enumerate(js):
            n2, m2 = noll_to_nm(jp)
            if m != m2 or (m != 0 and (j - jp) % 2):
                continue
            C[a, b] = (
                2.2424
                * (-1) ** ((n + n2 - 2 * m) // 2)
                * math.sqrt((n + 1) * (n2 + 1))
                * gamma((n + n2 - 5 / 3) / 2)
                / (gamma((n - n2 + 17 / 3) / 2) * gamma((n2 - n + 17 / 3) / 2) * gamma((n + n2 + 23 / 3) / 2))
            )
    C.setflags(write=False)
    return C
