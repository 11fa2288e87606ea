"""The hoisted kernels.line_correlation against a plain sample-by-sample reference."""

import math

import numpy as np
import pytest

from pwlreg.core.kernels import line_correlation


def _reference(target, patch, offsets, start, step, normal, linear, lengths, bands):
    """Sample by sample, as the kernel's docstring says: numpy over a patch's offsets, the sums
    in offset order (the kernel's order, so the comparison can be exact)."""
    t = target.astype(np.float64)
    h, w = t.shape
    n_off = len(offsets)
    out = np.full((len(start), int(lengths.max()), len(bands)), np.nan)
    for i in range(len(start)):
        pm = 0.0
        for value in patch[i]:
            pm += value
        pm /= n_off
        zero_mean = patch[i] - pm
        pv = 0.0
        for z in zero_mean:
            pv += z * z
        for s in range(lengths[i]):
            for b, band in enumerate(bands):
                cx = start[i, 0] + s * step[i, 0] + band * normal[i, 0]
                cy = start[i, 1] + s * step[i, 1] + band * normal[i, 1]
                x = cx + linear[i, 0, 0] * offsets[:, 0] + linear[i, 0, 1] * offsets[:, 1]
                y = cy + linear[i, 1, 0] * offsets[:, 0] + linear[i, 1, 1] * offsets[:, 1]
                if not np.all((x >= 0) & (y >= 0) & (x <= w - 1.0) & (y <= h - 1.0)):
                    out[i, s, b] = -1.0
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
                var = sxx - sx * sx / n_off
                out[i, s, b] = -1.0 if var <= 1e-9 or pv <= 1e-9 else sxp / math.sqrt(var * pv)
    return out


def _inputs(seed, offsets, n=60, length=24):
    """Candidates as core.refine makes them, some near or across the borders, a few flat."""
    rng = np.random.default_rng(seed)
    h, w = 90, 120
    target = rng.uniform(0, 255, (h, w)).astype(np.float32)
    target[60:, :40] = 77.0  # a flat corner: var 0 there
    patch = rng.uniform(0, 255, (n, len(offsets)))
    patch[:3] = 12.5  # flat patches: pv 0
    start = rng.uniform([-10, -10], [w + 10, h + 10], (n, 2))
    # On a grid of half-side 6, the samples of band 0 reach the first and last row and column.
    start[3] = [6.0, 6.0]
    start[4] = [w - 7.0, h - 7.0]
    start[5:10] = rng.uniform([5, 62], [35, 85], (5, 2))  # in the flat corner
    angle = rng.uniform(0, 2 * np.pi, n)
    step = np.column_stack([np.cos(angle), np.sin(angle)])
    normal = np.column_stack([-np.sin(angle), np.cos(angle)])
    linear = np.eye(2) + rng.normal(0, 0.15, (n, 2, 2))
    linear[3:5] = np.eye(2)
    step[3:5] = [1.0, 0.0]
    normal[3:5] = [0.0, 1.0]
    lengths = rng.integers(1, length + 1, n)
    return target, patch, offsets, start, step, normal, linear, lengths


def _grid(half, spacing):
    g = np.arange(-half, half + 1, spacing, dtype=np.float64)
    gu, gv = np.meshgrid(g, g)
    return np.column_stack([gu.ravel(), gv.ravel()])


@pytest.mark.parametrize(
    "offsets, bands",
    [
        (_grid(6, 2), np.array([-2.0, 0.0, 2.0])),  # core.refine's coarse pass
        (_grid(6, 1), np.arange(-2.0, 3.0)),  # and its fine one
        # Offsets that are no grid: the bounds of their box are not all reached.
        (np.random.default_rng(9).uniform(-5, 5, (30, 2)), np.array([0.0, 1.5])),
    ],
    ids=["coarse grid", "fine grid", "scattered offsets"],
)
def test_line_correlation_is_the_sample_by_sample_computation_bit_for_bit(offsets, bands):
    for seed in range(3):
        args = _inputs(seed, offsets)
        lengths = args[-1]
        out = np.full((len(lengths), int(lengths.max()), len(bands)), np.nan)
        line_correlation(*args, bands, out)
        want = _reference(*args, bands)
        written = np.arange(out.shape[1])[None, :, None] < lengths[:, None, None]
        written = np.broadcast_to(written, out.shape)
        np.testing.assert_array_equal(out[written], want[written])
        # Every branch is exercised: outside, flat, and correlations of both signs.
        values = want[written]
        assert np.any(values == -1.0) and np.any((values > 0.2) & (values < 1))
        assert np.any((values < -0.2) & (values > -1))
