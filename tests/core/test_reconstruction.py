"""Affine reconstruction by factorization, and its PLY and glb files."""

from __future__ import annotations

import io
import json
import struct

import cv2
import numpy as np
import pytest
import trimesh

from pwlreg.core.formats.glb import encode_glb
from pwlreg.core.formats.ply import encode_ply
from pwlreg.core.reconstruction import affine_reconstruction


def rotation(rx: float, ry: float, rz: float) -> np.ndarray:
    """Rotation about x, then y, then z (degrees)."""
    (cx, cy, cz), (sx, sy, sz) = np.cos(np.radians([rx, ry, rz])), np.sin(np.radians([rx, ry, rz]))
    rot_x = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    rot_y = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rot_z = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rot_z @ rot_y @ rot_x


def scene(n: int = 80, seed: int = 0) -> np.ndarray:
    """A relief: a ridge and a bump over a 400 x 300 patch (units: pixels at the reference)."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform([-200, -150], [200, 150], (n, 2))
    z = 60 * np.exp(-((xy[:, 0] - 50) ** 2 + xy[:, 1] ** 2) / 8000) - 0.2 * np.abs(xy[:, 0])
    return np.column_stack([xy, z])


def affine_camera(points: np.ndarray, angles: tuple[float, float, float], scale: float,
                  offset: tuple[float, float]) -> np.ndarray:
    """Projection by an affine (weak-perspective) camera: rotate, drop depth, scale, shift."""
    return scale * (points @ rotation(*angles).T)[:, :2] + np.asarray(offset)


def affine_fit_residual(estimate: np.ndarray, truth: np.ndarray) -> float:
    """RMS distance between ``truth`` and the best affine transform of ``estimate`` onto it,
    relative to the spread of ``truth``."""
    design = np.column_stack([estimate, np.ones(len(estimate))])
    transform = np.linalg.lstsq(design, truth, rcond=None)[0]
    rms = np.sqrt(np.mean(np.sum((design @ transform - truth) ** 2, axis=1)))
    return float(rms / np.sqrt(np.mean(np.sum((truth - truth.mean(0)) ** 2, axis=1))))


def test_two_affine_views_give_the_scene_up_to_an_affine_transform():
    truth = scene()
    ref = affine_camera(truth, (0, 0, 0), 1.0, (320, 240))
    mov = affine_camera(truth, (6, -18, 3), 0.9, (300, 250))
    rec = affine_reconstruction(ref, mov)
    exact = affine_fit_residual(rec.points, truth)
    noise = np.random.default_rng(1).normal(0, 0.25, (2,) + ref.shape)
    noisy = affine_reconstruction(ref + noise[0], mov + noise[1])
    noisy_residual = affine_fit_residual(noisy.points, truth)
    print(f"\naffine reconstruction of a {len(truth)}-point relief: residual after the best "
          f"affine transform {exact:.2e} (exact views), {noisy_residual:.4f} (0.25 px noise) of "
          f"the scene's spread; reprojection {rec.residual:.2e} px and {noisy.residual:.3f} px; "
          f"singular values {np.array2string(rec.singular_values, precision=3)}")
    assert exact < 1e-9
    assert rec.residual < 1e-9 and rec.singular_values[3] < 1e-9 * rec.singular_values[0]
    assert noisy_residual < 0.02
    assert noisy.residual < 0.25
    # The frame: x, y are the reference axes, and the cameras reproject the points.
    assert np.allclose(rec.cameras[:2], np.eye(2, 3))
    assert np.allclose(rec.project(), np.column_stack([ref, mov]), atol=1e-6)
    assert np.allclose(rec.points[:, :2] + rec.offsets[:2], ref, atol=1e-6)
    # Depth is really recovered: a plane's reconstruction is no affine image of the relief.
    assert np.std(rec.points[:, 2]) > 0.05 * np.std(rec.points[:, :2])


def test_a_planar_scene_comes_out_flat():
    truth = scene()
    truth[:, 2] = 0.0
    ref = affine_camera(truth, (0, 0, 0), 1.0, (320, 240))
    mov = affine_camera(truth, (10, -20, 5), 1.1, (300, 250))
    rec = affine_reconstruction(ref, mov)
    assert np.std(rec.points[:, 2]) < 1e-6 * np.std(rec.points[:, :2])


def test_unfitted_points_are_placed_through_the_fitted_cameras():
    truth = scene(n=60)
    ref = affine_camera(truth, (0, 0, 0), 1.0, (320, 240))
    mov = affine_camera(truth, (4, 15, 0), 1.0, (310, 230))
    fitted = np.ones(len(truth), bool)
    fitted[:10] = False
    mov_wrong = mov.copy()
    mov_wrong[:10] += 40.0  # far off: would spoil the cameras if they were fitted to them
    rec = affine_reconstruction(ref, mov_wrong, fitted=fitted)
    assert rec.residual < 1e-9
    assert affine_fit_residual(rec.points[10:], truth[10:]) < 1e-9
    with pytest.raises(ValueError, match="at least 4"):
        affine_reconstruction(ref[:3], mov[:3])


def test_ply_parses_with_its_vertices_faces_and_colours():
    vertices = np.array([[0, 0, 0], [10, 0, 1], [0, 10, 2], [10, 10, 3.5]], float)
    faces = np.array([[0, 1, 2], [1, 3, 2]])
    colours = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255], [9, 9, 9]], np.uint8)
    data = encode_ply(vertices, faces, colors=colours, comments=("made by a test",))
    assert data.startswith(b"ply\nformat binary_little_endian 1.0\ncomment made by a test\n")
    mesh = trimesh.load(io.BytesIO(data), file_type="ply", process=False)
    assert np.allclose(mesh.vertices, vertices)
    assert np.array_equal(mesh.faces, faces)
    assert np.array_equal(mesh.visual.vertex_colors[:, :3], colours)
    with pytest.raises(ValueError):
        encode_ply(vertices, [[0, 1, 4]])


def glb_json(data: bytes) -> dict:
    magic, version, total = struct.unpack_from("<4sII", data)
    assert (magic, version, total) == (b"glTF", 2, len(data))
    length, kind = struct.unpack_from("<I4s", data, 12)
    assert kind == b"JSON" and length % 4 == 0
    return json.loads(data[20:20 + length])


def test_glb_parses_with_two_scenes_and_a_texture():
    positions = np.array([[0, 0, 0], [10, 0, 1], [0, -10, 2], [10, -10, 3.5]], float)
    uv = np.array([[0, 0], [1, 0], [0, 1], [1, 1]], float)
    image = np.zeros((32, 48, 3), np.uint8)
    image[:, :24] = (0, 0, 255)
    texture = cv2.imencode(".png", image)[1].tobytes()
    data = encode_glb(positions, [("final", [[0, 1, 2], [1, 3, 2]]), ("initial", [[0, 1, 3],
                                                                                  [0, 3, 2]])],
                      texcoords=uv, texture=texture, texture_mime="image/png")
    doc = glb_json(data)
    assert [s["name"] for s in doc["scenes"]] == ["final", "initial"] and doc["scene"] == 0
    assert doc["extensionsUsed"] == ["KHR_materials_unlit"]
    assert all(v["byteOffset"] % 4 == 0 for v in doc["bufferViews"])
    position = doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"]]
    assert position["min"] == [0, -10, 0] and position["max"] == [10, 0, 3.5]
    loaded = trimesh.load(io.BytesIO(data), file_type="glb", process=False)
    assert loaded.graph.nodes_geometry == ["final"]  # the default scene
    assert sorted(loaded.geometry) == ["final", "initial"]
    final, initial = loaded.geometry["final"], loaded.geometry["initial"]
    assert np.allclose(final.vertices, positions) and np.allclose(initial.vertices, positions)
    assert np.array_equal(final.faces, [[0, 1, 2], [1, 3, 2]])
    assert np.array_equal(initial.faces, [[0, 1, 3], [0, 3, 2]])
    assert np.allclose(final.visual.uv, uv * [1, -1] + [0, 1])  # trimesh's v points up
    tex = np.asarray(final.visual.material.baseColorTexture)
    assert tex.shape[:2] == (32, 48) and tuple(tex[0, 0, :3]) == (255, 0, 0)
