"""PLY (Stanford polygon file), binary little-endian: a triangle mesh with optional vertex
colours. The reconstruction's results are written with it (:mod:`pwlreg.core.reconstruction`).
"""

from __future__ import annotations

import numpy as np


def encode_ply(
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    colors: np.ndarray | None = None,
    comments: tuple[str, ...] = (),
) -> bytes:
    """PLY bytes of a triangle mesh.

    Parameters
    ----------
    vertices : ndarray, shape (N, 3)
        Positions, written as float32 ``x y z``.
    faces : ndarray, shape (T, 3)
        Vertex indices of each triangle, written as ``vertex_indices`` lists (uchar count,
        int32 indices).
    colors : ndarray of uint8, shape (N, 3), optional
        Per-vertex ``red green blue``.
    comments : tuple of str
        One header comment line each (no line breaks).

    Returns
    -------
    bytes
    """
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(f) and (f.min() < 0 or f.max() >= len(v)):
        raise ValueError("a face refers to a vertex that does not exist")
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    props = ["property float x", "property float y", "property float z"]
    if colors is not None:
        c = np.asarray(colors, dtype=np.uint8).reshape(-1, 3)
        if len(c) != len(v):
            raise ValueError(f"{len(c)} colours for {len(v)} vertices")
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
        props += ["property uchar red", "property uchar green", "property uchar blue"]
    if any("\n" in c or "\r" in c for c in comments):
        raise ValueError("a PLY comment must be one line")
    records = np.empty(len(v), dtype=fields)
    for i, axis in enumerate("xyz"):
        records[axis] = v[:, i]
    if colors is not None:
        for i, band in enumerate(("red", "green", "blue")):
            records[band] = c[:, i]
    face_records = np.empty(len(f), dtype=[("n", "u1"), ("idx", "<i4", (3,))])
    face_records["n"] = 3
    face_records["idx"] = f
    header = "\n".join(
        ["ply", "format binary_little_endian 1.0"]
        + [f"comment {c}" for c in comments]
        + [f"element vertex {len(v)}", *props]
        + [f"element face {len(f)}", "property list uchar int vertex_indices", "end_header"]
    )
    return (header + "\n").encode("ascii") + records.tobytes() + face_records.tobytes()
