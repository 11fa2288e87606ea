"""The residual flow (:mod:`core.flow`) on images of every shape DIS meets."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import numpy as np
import pytest

from pwlreg.core.flow import coarsest_scale, flow_scale, residual_flows

# Run in a child process: before the finest scale was bounded by DIS's coarsest one, these
# shapes crashed the interpreter inside OpenCV, which would take the test session with it.
THIN_STRIPS = """
import cv2, numpy as np
from pwlreg.core.flow import residual_flows
rng = np.random.default_rng(0)
for h, w in ((40, 1500), (48, 1500), (60, 1500), (1500, 40), (9, 1500)):
    big = cv2.GaussianBlur((rng.random((h + 8, w + 8)) * 255).astype(np.uint8), (0, 0), 2.0)
    big = cv2.normalize(big, None, 0, 255, cv2.NORM_MINMAX)
    ref = np.ascontiguousarray(big[4:4 + h, 4:4 + w])
    mov = np.ascontiguousarray(big[4:4 + h, 5:5 + w])
    forward, backward = residual_flows(ref, mov)
    inner = forward[h // 4: h - h // 4 or None, w // 4: w - w // 4 or None]
    print(h, w, float(np.median(inner[..., 0])), float(np.median(inner[..., 1])))
"""


def test_thin_strips_get_a_flow_instead_of_a_crash() -> None:
    done = subprocess.run([sys.executable, "-c", textwrap.dedent(THIN_STRIPS)],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    rows = [line.split() for line in done.stdout.splitlines()]
    assert len(rows) == 5
    for h, w, dx, dy in rows:
        # The moving strip is the reference moved one pixel left: its flow is -1 in x.
        assert abs(float(dx) + 1.0) < 0.3, (h, w, dx)
        assert abs(float(dy)) < 0.3, (h, w, dy)


@pytest.mark.parametrize("shape", [(6, 100), (100, 7), (8, 8), (2, 2)])
def test_images_smaller_than_a_patch_are_not_measured(shape: tuple[int, int]) -> None:
    image = np.full(shape, 128, np.uint8)
    forward, backward = residual_flows(image, image)
    assert forward.shape == backward.shape == (*shape, 2)
    assert np.isnan(forward).all() and np.isnan(backward).all()


@pytest.mark.parametrize("shape", [(40, 1500), (480, 640), (768, 1024), (2048, 3072), (12, 12)])
def test_the_finest_scale_never_passes_the_coarsest(shape: tuple[int, int]) -> None:
    assert 0 <= flow_scale(shape) <= coarsest_scale(shape)
    assert 0 <= flow_scale(shape, side=64) <= coarsest_scale(shape)


def test_the_coarsest_scale_is_opencvs_on_ordinary_images() -> None:
    # min(round(log2(longer / 32)), floor(log2(shorter / 8))), OpenCV's DIS with 8-px patches.
    assert coarsest_scale((480, 640)) == 4
    assert coarsest_scale((768, 1024)) == 5
    assert coarsest_scale((40, 1500)) == 2
    assert flow_scale((768, 1024)) == 2  # 1024 / 4 = 256 <= 320, as before the bound
