"""Resampling the moving image through a piecewise-affine map.

Coordinates are pixels, x right, y down, (0, 0) the centre of the top-left pixel. Resampling is
bilinear in double precision (:mod:`core.kernels`).
"""

from __future__ import annotations

import numpy as np

from pwlreg.core import kernels
from pwlreg.core.raster import affine_maps, rasterize


def piecewise_map(
    reference_vertices: np.ndarray,
    moving_vertices: np.ndarray,
    triangles: np.ndarray,
    shape: tuple[int, int],
    *,
    dtype: type = np.float64,
    outside: float = np.nan,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Dense piecewise-affine map from the reference grid to the moving image.

    Parameters
    ----------
    reference_vertices, moving_vertices : ndarray, shape (N, 2)
        Vertex coordinates in pixels (quantized, as in :class:`core.mesh.Mesh`).
    triangles : ndarray, shape (T, 3)
        Vertex indices.
    shape : (int, int)
        ``(height, width)`` of the reference grid.
    dtype : numpy float type
        Of the maps (float32 for ``cv2.remap``: the float64 positions rounded once).
    outside : float
        Value of the maps outside the mesh.

    Returns
    -------
    map_x, map_y : ndarray of ``dtype``, shape (H, W)
        Position in the moving image of each reference pixel; ``outside`` outside the mesh.
    label : ndarray of int32, shape (H, W)
        Index of the triangle owning each pixel, -1 outside the mesh.
    """
    ref = np.asarray(reference_vertices, dtype=np.float64)
    mov = np.asarray(moving_vertices, dtype=np.float64)
    tris = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    maps = affine_maps(ref[tris], mov[tris])
    spans = rasterize(ref[tris], shape)
    map_x = np.full(shape, outside, dtype=dtype)
    map_y = np.full(shape, outside, dtype=dtype)
    label = np.full(shape, -1, dtype=np.int32)
    kernels.fill_spans(spans.triangle, spans.y, spans.x0, spans.length, maps, map_x, map_y, label)
    return map_x, map_y, label


def warp_image(
    moving: np.ndarray,
    reference_vertices: np.ndarray,
    moving_vertices: np.ndarray,
    triangles: np.ndarray,
    shape: tuple[int, int],
) -> np.ndarray:
    """The moving image resampled into the reference frame through the mesh, with alpha.

    Every band is kept and the dtype is preserved; an alpha band is appended (full scale where
    the reference pixel lies inside the mesh and maps inside the moving image, 0 elsewhere).

    Parameters
    ----------
    moving : ndarray, shape (H', W') or (H', W', C)
        Moving image, uint8 or uint16; grey, BGR or BGRA (an existing alpha band is treated as
        data and multiplied into the output alpha).
    reference_vertices, moving_vertices, triangles
        The mesh (see :func:`piecewise_map`).
    shape : (int, int)
        ``(height, width)`` of the reference image.

    Returns
    -------
    ndarray, shape (H, W, 2) for grey input or (H, W, 4) for colour
        Grey+alpha or BGRA, dtype of ``moving``.
    """
    height, width = int(shape[0]), int(shape[1])
    src = moving if moving.ndim == 3 else moving[:, :, None]
    colour = 3 if src.shape[2] == 4 else src.shape[2]
    ref = np.asarray(reference_vertices, dtype=np.float64)
    mov = np.asarray(moving_vertices, dtype=np.float64)
    tris = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    out = np.zeros((height, width, colour + 1), dtype=moving.dtype)
    if len(tris):
        kernels.warp(
            np.ascontiguousarray(ref[tris]),
            np.ascontiguousarray(mov[tris]),
            np.ascontiguousarray(src),
            out,
            np.iinfo(moving.dtype).max,
            outer_edge_flags(tris),
        )
    return out


def outer_edge_flags(triangles: np.ndarray) -> np.ndarray:
    """Per triangle, bit ``e`` set when its edge from vertex ``e`` to ``e + 1`` is on the mesh's
    outline (no other triangle shares it)."""
    tris = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    a = tris
    b = np.roll(tris, -1, axis=1)
    keys = np.minimum(a, b) * (tris.max(initial=0) + 1) + np.maximum(a, b)  # (T, 3)
    uniq, counts = np.unique(keys, return_counts=True)
    single = counts[np.searchsorted(uniq, keys)] == 1
    return (single * np.array([1, 2, 4])).sum(axis=1).astype(np.int64)
