"""Binary glTF 2.0 (``.glb``): triangle meshes sharing one vertex set, optionally textured with
one image, each mesh in a scene of its own.

The layout follows the glTF 2.0 specification: a 12-byte header (``glTF``, version 2, total
length), a JSON chunk padded with spaces and a binary chunk padded with zeros, both to 4 bytes;
every buffer view starts on a 4-byte boundary. Materials are unlit
(``KHR_materials_unlit``): the texture is a photograph, already lit.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Sequence

import numpy as np

_FLOAT, _UINT32 = 5126, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_UNLIT = "KHR_materials_unlit"


def _pad(data: bytes, fill: bytes) -> bytes:
    return data + fill * (-len(data) % 4)


def encode_glb(
    positions: np.ndarray,
    meshes: Sequence[tuple[str, np.ndarray]],
    *,
    texcoords: np.ndarray | None = None,
    texture: bytes | None = None,
    texture_mime: str = "image/jpeg",
    generator: str = "pwlreg",
) -> bytes:
    """GLB bytes of triangle meshes over shared vertices.

    Parameters
    ----------
    positions : ndarray, shape (N, 3)
        Vertex positions (float32 in the file), in glTF's frame: right-handed, y up.
    meshes : sequence of (str, ndarray of shape (T, 3))
        Name and triangles (vertex indices) of each mesh; mesh ``i`` is the only node of scene
        ``i``, and scene 0 is the default one.
    texcoords : ndarray, shape (N, 2), optional
        Texture coordinates (``TEXCOORD_0``; (0, 0) the top-left corner of the image, u right,
        v down). Needed with ``texture``.
    texture : bytes, optional
        Encoded image (PNG or JPEG) the meshes are textured with.
    texture_mime : str
        ``image/jpeg`` or ``image/png``.
    generator : str
        ``asset.generator``.

    Returns
    -------
    bytes
    """
    pos = np.ascontiguousarray(np.asarray(positions, dtype=np.float32).reshape(-1, 3))
    if texture is not None and texcoords is None:
        raise ValueError("a texture needs texture coordinates")
    if texture_mime not in ("image/jpeg", "image/png"):
        raise ValueError(f"glTF images are image/jpeg or image/png, not {texture_mime}")
    binary = bytearray()
    views: list[dict] = []
    accessors: list[dict] = []

    def add_view(data: bytes, target: int | None = None) -> int:
        binary.extend(b"\0" * (-len(binary) % 4))
        view = {"buffer": 0, "byteOffset": len(binary), "byteLength": len(data)}
        if target is not None:
            view["target"] = target
        binary.extend(data)
        views.append(view)
        return len(views) - 1

    def add_accessor(array: np.ndarray, kind: str, component: int, target: int,
                     bounds: bool = False) -> int:
        accessor = {"bufferView": add_view(array.tobytes(), target), "componentType": component,
                    "count": len(array), "type": kind}
        if bounds:
            accessor["min"] = array.min(axis=0).tolist()
            accessor["max"] = array.max(axis=0).tolist()
        accessors.append(accessor)
        return len(accessors) - 1

    attributes = {"POSITION": add_accessor(pos, "VEC3", _FLOAT, _ARRAY_BUFFER, bounds=True)}
    doc: dict = {"asset": {"version": "2.0", "generator": generator}}
    material = None
    if texcoords is not None:
        uv = np.ascontiguousarray(np.asarray(texcoords, dtype=np.float32).reshape(-1, 2))
        if len(uv) != len(pos):
            raise ValueError(f"{len(uv)} texture coordinates for {len(pos)} vertices")
        attributes["TEXCOORD_0"] = add_accessor(uv, "VEC2", _FLOAT, _ARRAY_BUFFER)
    if texture is not None:
        doc["images"] = [{"bufferView": add_view(texture), "mimeType": texture_mime}]
        doc["samplers"] = [{"magFilter": 9729, "minFilter": 9987, "wrapS": 33071,
                            "wrapT": 33071}]
        doc["textures"] = [{"sampler": 0, "source": 0}]
        doc["materials"] = [{
            "name": "image",
            "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}, "metallicFactor": 0.0,
                                     "roughnessFactor": 1.0},
            "doubleSided": True,
            "extensions": {_UNLIT: {}},
        }]
        doc["extensionsUsed"] = [_UNLIT]
        material = 0
    gltf_meshes, nodes, scenes = [], [], []
    for name, triangles in meshes:
        tris = np.ascontiguousarray(np.asarray(triangles, dtype=np.uint32).reshape(-1))
        if len(tris) and int(tris.max()) >= len(pos):
            raise ValueError(f"mesh {name!r} refers to a vertex that does not exist")
        primitive = {"attributes": attributes, "mode": 4,
                     "indices": add_accessor(tris, "SCALAR", _UINT32, _ELEMENT_ARRAY_BUFFER)}
        if material is not None:
            primitive["material"] = material
        gltf_meshes.append({"name": name, "primitives": [primitive]})
        nodes.append({"name": name, "mesh": len(gltf_meshes) - 1})
        scenes.append({"name": name, "nodes": [len(nodes) - 1]})
    binary.extend(b"\0" * (-len(binary) % 4))
    doc.update(scene=0, scenes=scenes, nodes=nodes, meshes=gltf_meshes, accessors=accessors,
               bufferViews=views, buffers=[{"byteLength": len(binary)}])
    json_chunk = _pad(json.dumps(doc, separators=(",", ":")).encode("utf-8"), b" ")
    total = 12 + 8 + len(json_chunk) + 8 + len(binary)
    return b"".join((
        struct.pack("<4sII", b"glTF", 2, total),
        struct.pack("<I4s", len(json_chunk), b"JSON"), json_chunk,
        struct.pack("<I4s", len(binary), b"BIN\0"), bytes(binary),
    ))
