"""kernels.strip_correlation against a plain sample-by-sample reference."""

import math

import numpy as np
import pytest

from pwlreg.core.kernels import strip_correlation


def _reference(target, patch, step, start, direction, normal, lengths, bands):
    """As the kernel's docstring says, one correlation at a time: the target sampled at each
    lattice point of each position and band (the sums in lattice order, the kernel's order, so
    the comparison can be exact)."""
    t = target.astype(np.float64)
    h, w = t.shape
    n = patch.shape[1]
    m = n // 2
    lattice = step * (np.arange(n) - m)
    out = np.full((len(start), int(lengths.max()), len(bands)), np.nan)
    for i in range(len(start)):
        values = patch[i].ravel()
        pm = 0.0
        for value in values:
            pm += value
        pm /= n * n
        zero_mean = values - pm
        pv = 0.0
        for z in zero_mean:
            pv += z * z
        for s in range(lengths[i]):
            for q, band in enumerate(bands):
                along = np.repeat(s + lattice, n)
                across = np.tile(band + lattice, n)
                x = start[i, 0] + along * direction[i, 0] + across * normal[i, 0]
                y = start[i, 1] + along * direction[i, 1] + across * normal[i, 1]
                if not np.all((x >= 0) & (y >= 0) & (x <= w - 1.0) & (y <= h - 1.0)):
                    out[i, s, q] = -1.0
                    continue
                x0 = np.minimum(x.astype(np.int64), w - 2)
                y0 = np.minimum(y.astype(np.int64), h - 2)
                fx, fy = x - x0, y - y0
                v = ((t[y0, x0] * (1.0 - fx) + t[y0, x0 + 1] * fx) * (1.0 - fy)
                     + (t[y0 + 1, x0] * (1.0 - fx) + t[y0 + 1, x0 + 1] * fx) * fy)
                sx = sxx = sxp = 0.0
                for value, z in zip(v.tolist(), zero_mean.tolist(), strict=True):
                    sx += value
                    sxx += value * value
                    sxp += value * z
                var = sxx - sx * sx / (n * n)
                out[i, s, q] = -1.0 if var <= 1e-9 or pv <= 1e-9 else sxp / math.sqrt(var * pv)
    return out


def _inputs(seed, n_patch, n=60, length=24):
    """Candidates as core.refine makes them, some near or across the borders, a few flat."""
    rng = np.random.default_rng(seed)
    h, w = 90, 120
    target = rng.uniform(0, 255, (h, w)).astype(np.float32)
    target[60:, :40] = 77.0  # a flat corner: var 0 there
    patch = rng.uniform(0, 255, (n, n_patch, n_patch))
    patch[:3] = 12.5  # flat patches: pv 0
    start = rng.uniform([-10, -10], [w + 10, h + 10], (n, 2))
    # With a lattice of half-side 6 along the axes, band 0 reaches the first and last row and
    # column.
    start[3] = [6.0, 6.0]
    start[4] = [w - 7.0 - length, h - 7.0]
    start[5:10] = rng.uniform([5, 62], [35, 85], (5, 2))  # in the flat corner
    angle = rng.uniform(0, 2 * np.pi, n)
    direction = np.column_stack([np.cos(angle), np.sin(angle)])
    normal = np.column_stack([-np.sin(angle), np.cos(angle)])
    direction[3:5] = [1.0, 0.0]
    normal[3:5] = [0.0, 1.0]
    lengths = rng.integers(1, length + 1, n)
    return target, patch, start, direction, normal, lengths


@pytest.mark.parametrize(
    "n_patch, step, bands",
    [(7, 2, np.array([0])), (13, 1, np.arange(-2, 3)), (5, 3, np.array([-1, 0]))],
    ids=["coarse pass", "fine pass", "other lattice"],
)
def test_strip_correlation_is_the_sample_by_sample_computation_bit_for_bit(n_patch, step, bands):
    for seed in range(3):
        target, patch, start, direction, normal, lengths = _inputs(seed, n_patch)
        out = np.full((len(lengths), int(lengths.max()), len(bands)), np.nan)
        strip_correlation(target, patch, step, start, direction, normal, lengths, bands, out)
        want = _reference(target, patch, step, start, direction, normal, lengths, bands)
        written = np.arange(out.shape[1])[None, :, None] < lengths[:, None, None]
        written = np.broadcast_to(written, out.shape)
        np.testing.assert_array_equal(out[written], want[written])
        # Every branch is exercised: outside, flat, and correlations of both signs.
        values = want[written]
        assert np.any(values == -1.0) and np.any((values > 0.2) & (values < 1))
        assert np.any((values < -0.2) & (values > -1))
