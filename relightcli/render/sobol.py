"""Scrambled Sobol points for the integrator, without scipy.stats (whose import alone takes
~0.8 s of a one-photo process).

The sequence is Sobol's with Joe and Kuo's direction numbers (new-joe-kuo-6.21201, the first
MAX_DIMENSIONS dimensions), in Gray-code order; the unscrambled points equal
scipy.stats.qmc.Sobol(scramble=False)'s (tests/render/test_sobol.py). The scramble is a random
linear matrix scramble (each dimension's direction numbers multiplied, over GF(2), by a random
lower-triangular bit matrix with a unit diagonal) followed by a random digital shift: it keeps
the points a (t, m, s)-net and makes each one uniform on [0, 1).
"""

from __future__ import annotations

import numpy as np

BITS = 32
# Joe & Kuo's primitive polynomials and initial direction numbers, dimensions 2..16:
# (degree s, coefficients a, initial m_1..m_s). Dimension 1 is the van der Corput sequence.
_DIRECTIONS = (
    (1, 0, (1,)),
    (2, 1, (1, 3)),
    (3, 1, (1, 3, 1)),
    (3, 2, (1, 1, 1)),
    (4, 1, (1, 1, 3, 3)),
    (4, 4, (1, 3, 5, 13)),
    (5, 2, (1, 1, 5, 5, 17)),
    (5, 4, (1, 1, 5, 5, 5)),
    (5, 7, (1, 1, 7, 11, 19)),
    (5, 11, (1, 1, 5, 1, 1)),
    (5, 13, (1, 1, 1, 3, 11)),
    (5, 14, (1, 3, 5, 5, 31)),
    (6, 1, (1, 3, 3, 9, 7, 49)),
    (6, 13, (1, 1, 1, 15, 21, 21)),
    (6, 16, (1, 3, 1, 13, 27, 49)),
)
MAX_DIMENSIONS = len(_DIRECTIONS) + 1


def direction_numbers(dims: int) -> np.ndarray:
    """(dims, BITS) uint64: v[d, k], the k-th direction number of dimension d, its bits
    aligned to the top of a BITS-bit integer."""
    if not 1 <= dims <= MAX_DIMENSIONS:
        raise ValueError(f"Sobol points need 1..{MAX_DIMENSIONS} dimensions, got {dims}")
    v = np.zeros((dims, BITS), dtype=np.uint64)
    v[0] = [1 << (BITS - 1 - k) for k in range(BITS)]
    for d in range(1, dims):
        s, a, m = _DIRECTIONS[d - 1]
        m = list(m)
        for k in range(s, BITS):  # m_k = 2 a_1 m_{k-1} ^ 4 a_2 m_{k-2} ^ ... ^ 2^s m_{k-s} ^ m_{k-s}
            value = m[k - s] ^ (m[k - s] << s)
            for j in range(1, s):
                if (a >> (s - 1 - j)) & 1:
                    value ^= m[k - j] << j
            m.append(value)
        v[d] = [m[k] << (BITS - 1 - k) for k in range(BITS)]
    return v


def _scramble_matrix(v: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Each dimension's direction numbers times a random unit lower-triangular bit matrix."""
    dims = v.shape[0]
    shifts = np.arange(BITS - 1, -1, -1, dtype=np.uint64)  # bit i (from the top) at 2^(BITS-1-i)
    bits = ((v[:, :, None] >> shifts) & np.uint64(1)).astype(np.uint8)  # (dims, k, i)
    lower = np.tril(rng.integers(0, 2, size=(dims, BITS, BITS), dtype=np.uint8), -1)
    lower[:, np.arange(BITS), np.arange(BITS)] = 1
    scrambled = np.einsum("dij,dkj->dki", lower.astype(np.int64), bits.astype(np.int64)) & 1
    return (scrambled.astype(np.uint64) << shifts).sum(axis=2, dtype=np.uint64)


def sobol_points(dims: int, m: int, rng: np.random.Generator | None = None) -> np.ndarray:
    """(2**m, dims) float64 in [0, 1): the first 2**m Sobol points in Gray-code order,
    scrambled with `rng` (unscrambled, starting at 0, when it is None)."""
    if not 0 <= m <= BITS:
        raise ValueError(f"2**m Sobol points need 0 <= m <= {BITS}, got {m}")
    v = direction_numbers(dims)
    shift = np.zeros(dims, dtype=np.uint64)
    if rng is not None:
        v = _scramble_matrix(v, rng)
        shift = rng.integers(0, 2**BITS, size=dims, dtype=np.uint64)
    count = 2**m
    # Gray-code order: point i = point i-1 ^ v[the lowest set bit of i]
    index = np.arange(1, count, dtype=np.int64)
    lowest = np.log2(index & -index).astype(np.int64)
    points = np.empty((count, dims), dtype=np.uint64)
    points[0] = shift
    if count > 1:
        steps = v[:, lowest].T  # (count - 1, dims)
        points[1:] = np.bitwise_xor.accumulate(steps, axis=0) ^ shift
    return points.astype(np.float64) / 2.0**BITS
