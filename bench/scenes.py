"""Synthetic polyhedral scenes seen from two viewpoints, with exact ground truth.

A scene is a set of textured planar polygons (boxes, prisms, gabled houses, L-shaped buildings,
an open book, a small city, or one plane) rendered by a z-buffered ray caster from a reference and
a moving camera. Because the geometry is known exactly, every reference pixel has a known 3-D point,
a known scene plane and a known position in the moving image, and every conjugate point pair is a
true correspondence.

Three families are hard cases for automatic matching and for verdicts on a registration:

``"checker"``
    a tiled plaza: one ground plane covered by a checkerboard of tiles 15-25 px wide at 640x480
    (the pattern repeats every 20-35 px along the tile diagonals, 30-50 px along the rows, less
    where foreshortened), with only a very weak non-periodic component (about 1 % of the
    contrast), so that a match one period off looks as good as the true one.
``"checker_box"``
    the same tiled ground with one or two boxes standing on it.
``"occluder"``
    a building facade (brick wall with a window grid) seen roughly frontally, with 2-4 thin
    occluders (pillars, a kiosk) standing in front of it: they slide over the facade between the
    views (occlusion boundaries, disoccluded areas).

Two more hard cases are options rather than families: ``make_scene(..., overlap=0.5)`` shifts the
moving view sideways so that only about that fraction of the reference view is covisible (wide
baseline, partial overlap), and :func:`make_unrelated_pair` pairs the views of two unrelated scenes
(no pixel corresponds).

Conventions
-----------
* Pixel coordinates: x to the right, y down, (0, 0) is the centre of the top-left pixel; image
  ``(W, H)`` covers ``[-0.5, W - 0.5] x [-0.5, H - 0.5]``.
* World coordinates: right-handed, z up, the ground is the plane z = 0; lengths in arbitrary
  world units (a building is about 3-10 units).
* Camera coordinates: x right, y down, z forward (depth).
* Images: ``uint8``, ``(H, W)`` grey or ``(H, W, 3)`` BGR, as :mod:`core.imaging` expects.

Rendering
---------
Each pixel is the mean of ``supersample x supersample`` rays (box-filter anti-aliasing), then an
optional Gaussian blur (the same for both views) and independent Gaussian sensor noise per view.
Every polygon carries its own procedural texture defined in its plane coordinates, so a 3-D point
has the same albedo in both views. Shading is Lambertian (an ambient term plus one directional
light). The ``radiometric`` option changes the moving view only:

``"none"``
    same light, same response: a 3-D point has the same intensity in both views (up to noise).
``"lighting"``
    the light moves and the exposure and gamma change: each face gets its own gain (the paper's
    figure 6(b)).
``"monotone"``
    lighting plus a random monotone tone curve (gain, gamma, offset) per face.
``"nonmonotone"``
    lighting plus a random non-monotone tone curve per face and per colour channel (faces
    "recoloured", the paper's figure 6(a)); the intensity relation between views is still a
    function on each face, which mutual information tolerates and correlation does not.

All randomness comes from ``numpy.random.default_rng`` streams derived from ``(family, seed)``:
the same arguments give the same scene, bit for bit. Geometry, cameras, textures and radiometry do
not depend on the image size; the image noise and the sampled conjugate points do (and so, slightly,
does the sideways shift chosen for a requested ``overlap``, which is measured on the pixel grid).
"""

from __future__ import annotations

import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import cv2
import numpy as np
from scipy import ndimage

__all__ = [
    "FAMILIES",
    "Camera",
    "Plane",
    "Polygon",
    "Scene",
    "backproject",
    "make_scene",
    "make_unrelated_pair",
    "project",
]

FAMILIES: tuple[str, ...] = (
    "plane", "box", "prism", "gable", "lshape", "open_book", "city",
    "checker", "checker_box", "occluder",
)
"""Scene families accepted by :func:`make_scene`.

``plane`` is one textured plane (a control: any triangulation of exact points is exact under
affine cameras); ``checker`` is one plane too, a periodic tiled plaza (a trap for matchers); the
others are polyhedral and produce Delaunay edges that cross creases. ``checker``, ``checker_box``
and ``occluder`` are the hard cases described in the module docstring.
"""

CameraKind = Literal["affine", "perspective"]
Radiometric = Literal["none", "lighting", "monotone", "nonmonotone"]
ColorMode = Literal["gray", "bgr"]

_UP = np.array([0.0, 0.0, 1.0])
_BGR_TO_GRAY = np.array([0.114, 0.587, 0.299])


# --------------------------------------------------------------------------------------------
# Public data types
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Camera:
    """A camera looking at the scene: perspective (pinhole) or affine (weak perspective).

    Attributes
    ----------
    kind : {"affine", "perspective"}
        Projection model.
    rotation : ndarray, shape (3, 3)
        World-to-camera rotation; its rows are the camera x (right), y (down) and z (forward)
        axes in world coordinates.
    centre : ndarray, shape (3,)
        Camera centre (world units). For the affine camera it is the point whose depth is zero;
        rays are parallel to the optical axis.
    focal : float
        Focal length in pixels.
    principal : ndarray, shape (2,)
        Principal point ``(cx, cy)`` in pixels.
    reference_depth : float
        Depth (world units) at which the affine camera has the scale of the perspective one:
        the affine camera maps a point at camera coordinates ``(x, y, z)`` to
        ``(focal * x / reference_depth + cx, focal * y / reference_depth + cy)``.
    """

    kind: CameraKind
    rotation: np.ndarray
    centre: np.ndarray
    focal: float
    principal: np.ndarray
    reference_depth: float

    @property
    def matrix(self) -> np.ndarray:
        """(3, 4) projection matrix; for the affine camera its last row is ``(0, 0, 0, 1)``."""
        R, C = self.rotation, self.centre
        K = np.array(
            [[self.focal, 0.0, self.principal[0]], [0.0, self.focal, self.principal[1]], [0, 0, 1]]
        )
        if self.kind == "perspective":
            return K @ np.hstack([R, (-R @ C)[:, None]])
        s = self.focal / self.reference_depth
        top = np.hstack([s * R[:2], (s * -(R[:2] @ C) + self.principal)[:, None]])
        return np.vstack([top, [0.0, 0.0, 0.0, 1.0]])

    def depth(self, points: np.ndarray) -> np.ndarray:
        """Depth (world units along the optical axis) of ``(N, 3)`` world points."""
        return (np.asarray(points, dtype=np.float64) - self.centre) @ self.rotation[2]


@dataclass(frozen=True, eq=False)
class Plane:
    """A scene plane ``normal . X = offset`` (world units), and the polygons lying on it.

    Attributes
    ----------
    normal : ndarray, shape (3,)
        Unit normal (outward for solids, towards the reference camera for open sheets).
    offset : float
        Signed distance of the plane from the world origin along ``normal``.
    polygons : tuple of int
        Indices into :attr:`Scene.polygons` of the polygons on this plane.
    name : str
        Name of the first polygon on the plane, e.g. ``"ground"``, ``"house0.roof1"``.
    """

    normal: np.ndarray
    offset: float
    polygons: tuple[int, ...]
    name: str


@dataclass(frozen=True, eq=False)
class Polygon:
    """A planar polygon of the scene (a face of a solid, a page, the ground).

    Attributes
    ----------
    vertices : ndarray, shape (K, 3)
        Corners in world units, in order around the polygon (may be non-convex).
    plane : int
        Index of its plane in :attr:`Scene.planes`.
    name : str
        ``"<object>.<face>"``, e.g. ``"box0.top"``.
    material : str
        Texture kind: ``ground``, ``crate``, ``wall``, ``roof``, ``top``, ``page``, ``stripes``
        or ``tiles`` (a periodic checkerboard of tiles).
    """

    vertices: np.ndarray
    plane: int
    name: str
    material: str


@dataclass(frozen=True, eq=False)
class Scene:
    """Two rendered views of a polyhedral scene and their exact correspondence.

    Attributes
    ----------
    family, seed : str, int
        Arguments that generated the scene (``family`` is ``"unrelated"`` for
        :func:`make_unrelated_pair`).
    camera_kind, radiometric : str
        Projection model and radiometric change (see the module docstring).
    reference, moving : ndarray of uint8
        The two images, ``(H, W)`` grey or ``(H, W, 3)`` BGR.
    face : ndarray of int32, shape (H, W)
        Plane id (index into :attr:`planes`) of the surface seen at each reference pixel centre,
        -1 for background (sky).
    truth_x, truth_y : ndarray of float64, shape (H, W)
        True position (pixels) in the moving image of the 3-D point seen at each reference pixel
        centre; NaN on background. Defined even where the point is hidden in the moving view.
    covisible : ndarray of bool, shape (H, W)
        The reference pixel sees a scene point that is also visible in the moving view (not
        occluded there) and projects inside ``[0, W - 1] x [0, H - 1]`` of the moving image.
    face_moving : ndarray of int32, shape (H, W)
        Plane id seen at each moving pixel centre, -1 for background.
    planes : tuple of Plane
        Scene planes; coplanar polygons share one plane.
    polygons : tuple of Polygon
        Scene polygons.
    cameras : tuple of Camera
        ``(reference camera, moving camera)``.
    points_reference, points_moving : ndarray of float64, shape (N, 2)
        Conjugate points (pixels): the exact correspondences plus independent Gaussian noise of
        standard deviation ``point_noise`` in each image.
    points_reference_exact, points_moving_exact : ndarray of float64, shape (N, 2)
        The same points without noise: projections of the same 3-D points.
    points_world : ndarray of float64, shape (N, 3)
        The 3-D points.
    points_plane : ndarray of int32, shape (N,)
        Plane of each interior point; -1 for polyhedron corners (on two or more planes).
    info : dict
        Generation parameters (``size``, ``noise``, ``blur``, ``color``, ``point_noise``,
        ``baseline_deg``, ``distance_radii``, ``overlap_requested``: the ``overlap`` argument,
        None by default), the ``scene_radius`` (world units), the ``covisible_fraction`` of the
        reference pixels that see the scene, ``overlap_shift_px``: the sideways shift (pixels,
        at the reference depth) given to the moving view for a requested overlap, 0 otherwise,
        and ``unrelated``: True for :func:`make_unrelated_pair` (which adds its own keys),
        False otherwise.

    Notes
    -----
    Mesh correctness needs to know which planes a vertex lies on in 3-D, which the image
    cannot tell at occluding contours: use :meth:`vertex_planes` with
    :func:`bench.metrics.mesh_correctness`.
    """

    family: str
    seed: int
    camera_kind: str
    radiometric: str
    reference: np.ndarray
    moving: np.ndarray
    face: np.ndarray
    truth_x: np.ndarray
    truth_y: np.ndarray
    covisible: np.ndarray
    face_moving: np.ndarray
    planes: tuple[Plane, ...]
    polygons: tuple[Polygon, ...]
    cameras: tuple[Camera, Camera]
    points_reference: np.ndarray
    points_moving: np.ndarray
    points_reference_exact: np.ndarray
    points_moving_exact: np.ndarray
    points_world: np.ndarray
    points_plane: np.ndarray
    info: dict = field(default_factory=dict)

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)`` of both images."""
        return self.face.shape

    @property
    def is_corner(self) -> np.ndarray:
        """(N,) bool: the conjugate point is a polyhedron corner (not a face-interior point)."""
        return self.points_plane < 0

    @property
    def point_planes(self) -> np.ndarray:
        """(N, P) bool: conjugate point ``i`` lies on plane ``p`` (in 3-D, not just in the image).

        An interior point lies on one plane, a corner on two or more (a box's top corner on its
        top and two walls, a bottom corner also on the ground). Tolerance: 1e-6 scene radii.
        """
        tol = 1e-6 * float(self.info.get("scene_radius", 1.0))
        normals = np.array([p.normal for p in self.planes])
        offsets = np.array([p.offset for p in self.planes])
        return np.abs(self.points_world @ normals.T - offsets) <= tol

    def vertex_planes(self, reference_vertices: np.ndarray, tolerance: float = 0.05) -> np.ndarray:
        """Planes each mesh vertex lies on, for :func:`bench.metrics.mesh_correctness`.

        Mesh vertices are matched to the scene's conjugate points by reference position
        (nearest of :attr:`points_reference` within ``tolerance`` pixels), so vertices that a
        registration quantized, reordered or filtered still find their 3-D point.

        Parameters
        ----------
        reference_vertices : ndarray, shape (M, 2)
            Mesh vertices in the reference image (pixels).
        tolerance : float
            Matching distance in pixels (the core quantizes vertices to 1/256 px).

        Returns
        -------
        ndarray of bool, shape (M, P)
            Row ``i`` is :attr:`point_planes` of the matched point; all True (no constraint)
            for a vertex that matches no scene point.
        """
        verts = np.asarray(reference_vertices, dtype=np.float64).reshape(-1, 2)
        table = self.point_planes
        out = np.ones((len(verts), len(self.planes)), dtype=bool)
        if len(self.points_reference) == 0:
            return out
        d = np.hypot(verts[:, None, 0] - self.points_reference[None, :, 0],
                     verts[:, None, 1] - self.points_reference[None, :, 1])
        nearest = d.argmin(axis=1)
        found = d[np.arange(len(verts)), nearest] <= tolerance
        out[found] = table[nearest[found]]
        return out


# --------------------------------------------------------------------------------------------
# Projection and ray casting
# --------------------------------------------------------------------------------------------


def project(camera: Camera, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project world points into a camera.

    Parameters
    ----------
    camera : Camera
    points : ndarray, shape (N, 3)
        World points.

    Returns
    -------
    xy : ndarray, shape (N, 2)
        Pixel coordinates (x right, y down, (0, 0) the centre of the top-left pixel).
    depth : ndarray, shape (N,)
        Depth along the optical axis (world units); points with depth <= 0 are behind a
        perspective camera and their ``xy`` is meaningless.
    """
    X = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    cam = (X - camera.centre) @ camera.rotation.T
    depth = cam[:, 2]
    if camera.kind == "perspective":
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = camera.focal * cam[:, :2] / depth[:, None]
    else:
        xy = camera.focal * cam[:, :2] / camera.reference_depth
    return xy + camera.principal, depth


def _rays(camera: Camera, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Origins and directions such that ``origin + depth * direction`` is the point at ``depth``."""
    R, C = camera.rotation, camera.centre
    px = (x - camera.principal[0]) / camera.focal
    py = (y - camera.principal[1]) / camera.focal
    if camera.kind == "perspective":
        direction = px[:, None] * R[0] + py[:, None] * R[1] + R[2]
        origin = np.broadcast_to(C, direction.shape)
    else:
        d = camera.reference_depth
        origin = C + (d * px)[:, None] * R[0] + (d * py)[:, None] * R[1]
        direction = np.broadcast_to(R[2], origin.shape)
    return origin, direction


def _ray_dot(
    camera: Camera, x: np.ndarray, y: np.ndarray, w: np.ndarray
) -> tuple[np.ndarray | float, np.ndarray | float]:
    """``(origin . w, direction . w)`` of the rays through ``(x, y)`` without (N, 3) arrays."""
    R, C = camera.rotation, camera.centre
    px = (x - camera.principal[0]) / camera.focal
    py = (y - camera.principal[1]) / camera.focal
    r0, r1, r2, c = R[0] @ w, R[1] @ w, R[2] @ w, C @ w
    if camera.kind == "perspective":
        return c, px * r0 + py * r1 + r2
    d = camera.reference_depth
    return c + d * (px * r0 + py * r1), r2


def _plane_coordinates(
    camera: Camera, geometry: _Geometry, p: int, x: np.ndarray, y: np.ndarray, z: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Coordinates (a, b) in the plane axes of polygon ``p`` of the points at depth ``z``."""
    out = []
    for axis in geometry.axes[p]:
        o, d = _ray_dot(camera, x, y, axis)
        out.append(o + z * d - geometry.origin[p] @ axis)
    return out[0], out[1]


def backproject(
    camera: Camera, xy: np.ndarray, normal: np.ndarray, offset: float
) -> np.ndarray:
    """Intersect the rays through image points with the plane ``normal . X = offset``.

    Parameters
    ----------
    camera : Camera
    xy : ndarray, shape (N, 2)
        Image points (pixels).
    normal : ndarray, shape (3,)
        Plane normal (any length, consistent with ``offset``).
    offset : float
        Plane offset, world units times ``|normal|``.

    Returns
    -------
    ndarray, shape (N, 3)
        World points (NaN where the ray is parallel to the plane).
    """
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    origin, direction = _rays(camera, xy[:, 0], xy[:, 1])
    n = np.asarray(normal, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = (offset - origin @ n) / (direction @ n)
    return origin + z[:, None] * direction


@dataclass(frozen=True, eq=False)
class _Geometry:
    """Per-polygon arrays used by the ray caster."""

    polygons: tuple[Polygon, ...]
    normal: np.ndarray  # (P, 3) unit normal of each polygon (from its vertex order)
    offset: np.ndarray  # (P,)
    origin: np.ndarray  # (P, 3) in-plane origin
    axes: np.ndarray  # (P, 2, 3) in-plane orthonormal axes (u, v)
    outline: tuple[np.ndarray, ...]  # (K, 2) polygon in its (u, v) plane coordinates


def _newell_normal(vertices: np.ndarray) -> np.ndarray:
    v = np.asarray(vertices, dtype=np.float64)
    w = np.roll(v, -1, axis=0)
    n = np.array(
        [
            np.sum((v[:, 1] - w[:, 1]) * (v[:, 2] + w[:, 2])),
            np.sum((v[:, 2] - w[:, 2]) * (v[:, 0] + w[:, 0])),
            np.sum((v[:, 0] - w[:, 0]) * (v[:, 1] + w[:, 1])),
        ]
    )
    return n / np.linalg.norm(n)


def _plane_axes(normal: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """In-plane axes (u, v): for walls u horizontal and v up; otherwise u along the first edge."""
    if abs(normal[2]) < 0.9:
        u = np.cross(_UP, normal)
    else:
        u = vertices[1] - vertices[0]
        u = u - normal * (u @ normal)
    u = u / np.linalg.norm(u)
    v = np.cross(normal, u)
    return np.stack([u, v])


def _geometry(polygons: tuple[Polygon, ...]) -> _Geometry:
    normals, offsets, origins, axes, outlines = [], [], [], [], []
    for poly in polygons:
        n = _newell_normal(poly.vertices)
        ax = _plane_axes(n, poly.vertices)
        o = poly.vertices[0]
        normals.append(n)
        offsets.append(float(n @ o))
        origins.append(o)
        axes.append(ax)
        outlines.append((poly.vertices - o) @ ax.T)
    return _Geometry(
        polygons=polygons,
        normal=np.array(normals),
        offset=np.array(offsets),
        origin=np.array(origins),
        axes=np.array(axes),
        outline=tuple(outlines),
    )


def _inside(outline: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Even-odd point-in-polygon test of points ``(a, b)`` against ``outline`` (K, 2)."""
    inside = np.zeros(a.shape, dtype=bool)
    k = len(outline)
    for i in range(k):
        a0, b0 = outline[i]
        a1, b1 = outline[(i + 1) % k]
        if b0 == b1:
            continue
        crosses = (b0 > b) != (b1 > b)
        at = a0 + (b - b0) * (a1 - a0) / (b1 - b0)
        inside ^= crosses & (a < at)
    return inside


def _trace(
    camera: Camera, geometry: _Geometry, x: np.ndarray, y: np.ndarray, near: float = 1e-6
) -> tuple[np.ndarray, np.ndarray]:
    """Cast rays through image points and find the first polygon each one hits.

    Parameters
    ----------
    camera : Camera
    geometry : _Geometry
        Built from the scene polygons (internal).
    x, y : ndarray, shape (N,)
        Image points (pixels).
    near : float
        Hits at depth below this (world units) are ignored.

    Returns
    -------
    polygon : ndarray of int32, shape (N,)
        Index of the first polygon hit, -1 for none.
    depth : ndarray of float64, shape (N,)
        Its depth (world units), +inf for none.
    """
    x = np.asarray(x, dtype=np.float64).ravel()
    y = np.asarray(y, dtype=np.float64).ravel()
    n_rays = len(x)
    best = np.full(n_rays, np.inf)
    hit = np.full(n_rays, -1, dtype=np.int32)
    for p, poly in enumerate(geometry.polygons):
        xy, depth = project(camera, poly.vertices)
        if np.all(depth > near):
            lo, hi = xy.min(axis=0) - 1.0, xy.max(axis=0) + 1.0
            sel = np.flatnonzero((x >= lo[0]) & (x <= hi[0]) & (y >= lo[1]) & (y <= hi[1]))
        else:
            sel = np.arange(n_rays)
        if len(sel) == 0:
            continue
        xs, ys = x[sel], y[sel]
        on, dn = _ray_dot(camera, xs, ys, geometry.normal[p])
        dn = np.broadcast_to(dn, xs.shape)
        with np.errstate(divide="ignore", invalid="ignore"):
            z = (geometry.offset[p] - on) / dn
        ok = (np.abs(dn) > 1e-12) & (z > near) & (z < best[sel])
        if not np.any(ok):
            continue
        sel, z = sel[ok], z[ok]
        a, b = _plane_coordinates(camera, geometry, p, x[sel], y[sel], z)
        inside = _inside(geometry.outline[p], a, b)
        best[sel[inside]] = z[inside]
        hit[sel[inside]] = p
    return hit, best


# --------------------------------------------------------------------------------------------
# Scene geometry (families)
# --------------------------------------------------------------------------------------------


@dataclass
class _Face:
    vertices: np.ndarray
    name: str
    material: str


def _yaw_matrix(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _place(faces: list[_Face], yaw: float, shift: np.ndarray) -> list[_Face]:
    R = _yaw_matrix(yaw)
    return [_Face(f.vertices @ R.T + shift, f.name, f.material) for f in faces]


def _orient_outward(faces: list[_Face], interior: np.ndarray) -> list[_Face]:
    """Reverse faces of a convex solid whose vertex-order normal points inwards."""
    out = []
    for f in faces:
        n = _newell_normal(f.vertices)
        if n @ (f.vertices.mean(axis=0) - interior) < 0:
            f = _Face(f.vertices[::-1].copy(), f.name, f.material)
        out.append(f)
    return out


def _extrusion(footprint: np.ndarray, height: float, name: str, wall: str, top: str) -> list[_Face]:
    """Vertical walls and a flat top over a counter-clockwise footprint (K, 2) on z = 0."""
    fp = np.asarray(footprint, dtype=np.float64)
    k = len(fp)
    faces = []
    for i in range(k):
        p, q = fp[i], fp[(i + 1) % k]
        quad = np.array([[*p, 0.0], [*q, 0.0], [*q, height], [*p, height]])
        faces.append(_Face(quad, f"{name}.wall{i}", wall))
    faces.append(_Face(np.column_stack([fp, np.full(k, height)]), f"{name}.top", top))
    return faces


def _box(rng: np.random.Generator, name: str, scale: float = 1.0) -> list[_Face]:
    sx, sy = rng.uniform(3.0, 6.0, 2) * scale
    sz = rng.uniform(2.5, 5.0) * scale
    fp = np.array([[-sx, -sy], [sx, -sy], [sx, sy], [-sx, sy]]) / 2
    return _extrusion(fp, sz, name, "crate", "crate")


def _prism(rng: np.random.Generator, name: str, scale: float = 1.0) -> list[_Face]:
    if rng.uniform() < 0.5:
        # A vertical prism over a regular polygon.
        k = int(rng.integers(3, 7))
        r = rng.uniform(2.2, 3.5) * scale
        ang = np.arange(k) * 2 * np.pi / k + rng.uniform(0, 2 * np.pi / k)
        fp = r * np.column_stack([np.cos(ang), np.sin(ang)])
        return _extrusion(fp, rng.uniform(3.0, 6.0) * scale, name, "stripes", "top")
    # A triangular prism lying on a rectangular face (a tent / wedge).
    length = rng.uniform(5.0, 8.0) * scale
    width = rng.uniform(3.5, 6.0) * scale
    height = rng.uniform(2.5, 4.5) * scale
    ridge = rng.uniform(0.3, 0.7) * width  # asymmetric ridge position
    x0, x1, y0, y1 = -length / 2, length / 2, -width / 2, width / 2
    yr = y0 + ridge
    faces = [
        _Face(np.array([[x0, y0, 0], [x1, y0, 0], [x1, yr, height], [x0, yr, height]]),
              f"{name}.side0", "stripes"),
        _Face(np.array([[x0, yr, height], [x1, yr, height], [x1, y1, 0], [x0, y1, 0]]),
              f"{name}.side1", "stripes"),
        _Face(np.array([[x0, y0, 0], [x0, yr, height], [x0, y1, 0]]), f"{name}.end0", "crate"),
        _Face(np.array([[x1, y0, 0], [x1, y1, 0], [x1, yr, height]]), f"{name}.end1", "crate"),
    ]
    return _orient_outward(faces, np.array([0.0, 0.0, height / 3]))


def _gable(rng: np.random.Generator, name: str, scale: float = 1.0) -> list[_Face]:
    length = rng.uniform(6.0, 9.0) * scale
    width = rng.uniform(4.0, 6.0) * scale
    wall = rng.uniform(2.5, 4.0) * scale
    ridge = rng.uniform(1.5, 3.0) * scale
    x0, x1, y0, y1 = -length / 2, length / 2, -width / 2, width / 2
    zr = wall + ridge
    faces = [
        _Face(np.array([[x0, y0, 0], [x1, y0, 0], [x1, y0, wall], [x0, y0, wall]]),
              f"{name}.wall0", "wall"),
        _Face(np.array([[x0, y1, 0], [x1, y1, 0], [x1, y1, wall], [x0, y1, wall]]),
              f"{name}.wall1", "wall"),
        _Face(np.array([[x0, y0, 0], [x0, y1, 0], [x0, y1, wall], [x0, 0, zr], [x0, y0, wall]]),
              f"{name}.gable0", "wall"),
        _Face(np.array([[x1, y0, 0], [x1, y1, 0], [x1, y1, wall], [x1, 0, zr], [x1, y0, wall]]),
              f"{name}.gable1", "wall"),
        _Face(np.array([[x0, y0, wall], [x1, y0, wall], [x1, 0, zr], [x0, 0, zr]]),
              f"{name}.roof0", "roof"),
        _Face(np.array([[x0, y1, wall], [x1, y1, wall], [x1, 0, zr], [x0, 0, zr]]),
              f"{name}.roof1", "roof"),
    ]
    return _orient_outward(faces, np.array([0.0, 0.0, wall / 2]))


def _lshape(rng: np.random.Generator, name: str, scale: float = 1.0) -> list[_Face]:
    a = rng.uniform(6.0, 9.0) * scale  # outer sides
    b = rng.uniform(6.0, 9.0) * scale
    t = rng.uniform(0.35, 0.55)  # wing thickness as a fraction
    ta, tb = t * a, t * b
    fp = np.array([[0, 0], [a, 0], [a, tb], [ta, tb], [ta, b], [0, b]]) - np.array([a, b]) / 3
    return _extrusion(fp, rng.uniform(3.0, 6.0) * scale, name, "wall", "top")


def _page_pair(rng: np.random.Generator) -> list[_Face]:
    """Two rectangles hinged on the vertical z axis (an open book standing on its spine)."""
    opening = np.deg2rad(rng.uniform(100.0, 140.0))
    width = rng.uniform(8.0, 10.0)
    height = rng.uniform(9.0, 12.0)
    convex = rng.uniform() < 0.5  # spine towards the camera (convex) or away (concave)
    # The camera looks along +y; the pages open towards -y (concave) or +y (convex).
    side = 1.0 if convex else -1.0
    half = opening / 2
    d0 = np.array([-np.sin(half), side * np.cos(half), 0.0])
    d1 = np.array([np.sin(half), side * np.cos(half), 0.0])
    z0, z1 = -height / 2, height / 2
    faces = []
    for i, d in enumerate((d0, d1)):
        e = width * d
        quad = np.array([[0, 0, z0], [e[0], e[1], z0], [e[0], e[1], z1], [0, 0, z1]])
        faces.append(_Face(quad, f"book.page{i}", "page"))
    return faces


def _sheet(rng: np.random.Generator) -> list[_Face]:
    """One textured rectangle, tilted, facing the camera roughly along -y."""
    w, h = rng.uniform(16.0, 20.0), rng.uniform(13.0, 16.0)
    hw, hh = w / 2, h / 2
    quad = np.array([[-hw, 0, -hh], [hw, 0, -hh], [hw, 0, hh], [-hw, 0, hh]])
    tilt_x, tilt_z = np.deg2rad(rng.uniform(-25, 25)), np.deg2rad(rng.uniform(-25, 25))
    cx, sx = np.cos(tilt_x), np.sin(tilt_x)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    return [_Face(quad @ Rx.T @ _yaw_matrix(tilt_z).T, "sheet", "page")]


_BUILDERS: dict[str, Callable[..., list[_Face]]] = {
    "box": _box,
    "prism": _prism,
    "gable": _gable,
    "lshape": _lshape,
}


def _city(rng: np.random.Generator) -> list[_Face]:
    n = int(rng.integers(3, 6))
    slots = [(i, j) for i in range(3) for j in range(2)]
    order = rng.permutation(len(slots))[:n]
    kinds = ("box", "gable", "lshape", "prism")
    faces: list[_Face] = []
    spacing = 8.0
    for k, s in enumerate(order):
        i, j = slots[s]
        kind = kinds[int(rng.integers(len(kinds)))]
        solid = _BUILDERS[kind](rng, f"{kind}{k}", scale=0.75)
        centre = np.array([(i - 1) * spacing, (j - 0.5) * spacing, 0.0])
        centre[:2] += rng.uniform(-0.8, 0.8, 2)
        faces += _place(solid, rng.uniform(-0.35, 0.35), centre)
    return faces


def _plaza(rng: np.random.Generator) -> list[_Face]:
    """A square tiled plaza on z = 0, normal up (the whole ``checker`` scene)."""
    g = rng.uniform(9.0, 11.0)
    quad = np.array([[-g, -g, 0.0], [g, -g, 0.0], [g, g, 0.0], [-g, g, 0.0]])
    return [_Face(quad, "ground", "tiles")]


def _tiled_boxes(rng: np.random.Generator) -> list[_Face]:
    """One large or two smaller boxes side by side (``checker_box``; the ground is added later)."""
    n = int(rng.integers(1, 3))
    faces: list[_Face] = []
    for k in range(n):
        solid = _box(rng, f"box{k}", scale=1.3 if n == 1 else 0.8)
        # Two boxes of scale 0.8 have half-diagonals below 3.4: 9 units apart they never touch.
        centre = np.array([(k - (n - 1) / 2) * 9.0, 0.0, 0.0])
        centre[:2] += rng.uniform(-0.5, 0.5, 2)
        faces += _place(solid, rng.uniform(-0.6, 0.6), centre)
    return faces


def _pillar(rng: np.random.Generator, name: str) -> list[_Face]:
    """A thin square pillar (a pole, a lamp post) on z = 0."""
    w = rng.uniform(0.4, 0.6) / 2
    fp = np.array([[-w, -w], [w, -w], [w, w], [-w, w]])
    return _extrusion(fp, rng.uniform(4.5, 8.0), name, "top", "top")


def _kiosk(rng: np.random.Generator, name: str) -> list[_Face]:
    """A small box (a kiosk, a bin) on z = 0."""
    sx, sy = rng.uniform(2.2, 3.2) / 2, rng.uniform(1.4, 2.0) / 2
    fp = np.array([[-sx, -sy], [sx, -sy], [sx, sy], [-sx, sy]])
    return _extrusion(fp, rng.uniform(2.5, 3.2), name, "crate", "top")


def _facade_occluders(rng: np.random.Generator) -> list[_Face]:
    """A building whose facade (y = 0, facing -y) has 2-4 thin occluders standing before it."""
    length, depth, height = rng.uniform(22.0, 28.0), rng.uniform(4.0, 6.0), rng.uniform(8.0, 11.0)
    fp = np.array([[-length / 2, 0.0], [length / 2, 0.0], [length / 2, depth],
                   [-length / 2, depth]])
    faces = _extrusion(fp, height, "facade", "wall", "top")  # facade.wall0 is the front
    n = int(rng.integers(2, 5))
    kiosk = int(rng.integers(n)) if rng.uniform() < 0.6 else -1
    # Occluders spread along the facade (one per slot), 2.5-6 units in front of it.
    slots = (np.arange(n) + 0.5) / n - 0.5
    xs = 0.6 * length * (slots + rng.uniform(-0.25, 0.25, n) / n)
    for k in range(n):
        if k == kiosk:
            solid = _kiosk(rng, "kiosk")
        else:
            solid = _pillar(rng, f"pillar{k}")
        centre = np.array([xs[k], -rng.uniform(2.5, 6.0), 0.0])
        faces += _place(solid, rng.uniform(-0.3, 0.3), centre)
    return faces


def _family_faces(family: str, rng: np.random.Generator) -> tuple[list[_Face], bool]:
    """Faces of a family and whether it stands on a ground plane."""
    if family == "plane":
        return _sheet(rng), False
    if family == "checker":
        return _plaza(rng), False
    if family == "checker_box":
        return _tiled_boxes(rng), True
    if family == "occluder":
        return _facade_occluders(rng), True
    if family == "open_book":
        return _page_pair(rng), False
    if family == "city":
        return _city(rng), True
    solid = _BUILDERS[family](rng, f"{family}0")
    return _place(solid, rng.uniform(0, 2 * np.pi), np.zeros(3)), True


def _ground(centre: np.ndarray, radius: float, material: str = "ground") -> _Face:
    g = 6.0 * radius
    c = centre[:2]
    quad = np.array(
        [[c[0] - g, c[1] - g, 0], [c[0] + g, c[1] - g, 0], [c[0] + g, c[1] + g, 0],
         [c[0] - g, c[1] + g, 0]]
    )
    return _Face(quad, "ground", material)


# Ground material of the grounded families ("ground" unless listed).
_GROUND_MATERIAL = {"checker_box": "tiles"}
# Height of the point the cameras aim at, as a fraction of the scene height (grounded families).
_TARGET_HEIGHT = {"occluder": 0.5}


def _merge_planes(polygons: list[_Face]) -> tuple[tuple[Plane, ...], list[int]]:
    """Group coplanar polygons (same oriented plane within tolerance) into planes."""
    keys: list[tuple[np.ndarray, float]] = []
    members: list[list[int]] = []
    plane_of = []
    for i, f in enumerate(polygons):
        n = _newell_normal(f.vertices)
        d = float(n @ f.vertices[0])
        for k, (n2, d2) in enumerate(keys):
            if n @ n2 > 1 - 1e-9 and abs(d - d2) < 1e-6:
                members[k].append(i)
                plane_of.append(k)
                break
        else:
            keys.append((n, d))
            members.append([i])
            plane_of.append(len(keys) - 1)
    planes = tuple(
        Plane(normal=n, offset=d, polygons=tuple(m), name=polygons[m[0]].name)
        for (n, d), m in zip(keys, members, strict=True)
    )
    return planes, plane_of


# --------------------------------------------------------------------------------------------
# Cameras
# --------------------------------------------------------------------------------------------


def _look_at(target: np.ndarray, azimuth: float, elevation: float, distance: float,
             roll: float) -> tuple[np.ndarray, np.ndarray]:
    """Rotation (rows x right, y down, z forward) and centre of a camera aimed at ``target``.

    ``azimuth`` is measured from the -y axis (0 = looking along +y), ``elevation`` above the
    horizon, angles in radians.
    """
    back = np.array(
        [np.sin(azimuth) * np.cos(elevation), -np.cos(azimuth) * np.cos(elevation),
         np.sin(elevation)]
    )
    centre = target + distance * back
    forward = -back
    right = np.cross(forward, _UP)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    c, s = np.cos(roll), np.sin(roll)
    right, down = c * right + s * down, -s * right + c * down
    return np.stack([right, down, forward]), centre


_VIEW = {
    # family: (elevation range deg, azimuth range deg of the reference view)
    "plane": ((-10.0, 10.0), (-20.0, 20.0)),
    "open_book": ((0.0, 15.0), (-15.0, 15.0)),
    "city": ((30.0, 45.0), (-40.0, 40.0)),
    "checker": ((35.0, 55.0), (-180.0, 180.0)),
    "occluder": ((8.0, 18.0), (-20.0, 20.0)),
}
_DEFAULT_VIEW = ((25.0, 40.0), (-180.0, 180.0))
# Image half-size (as a fraction of min(W, H)) covered by the scene radius. The plaza is larger
# than the view (no sky): only its middle part is seen, in both views.
_FILL = {
    "plane": 0.75, "open_book": 0.7, "city": 0.75, "checker": 2.0, "checker_box": 0.45,
    "occluder": 0.8,
}


def _cameras(
    rng: np.random.Generator,
    family: str,
    kind: CameraKind,
    target: np.ndarray,
    radius: float,
    size: tuple[int, int],
    baseline: float,
    distance_radii: float,
) -> tuple[Camera, Camera]:
    width, height = size
    (el_lo, el_hi), (az_lo, az_hi) = _VIEW.get(family, _DEFAULT_VIEW)
    distance = distance_radii * radius
    fill = _FILL.get(family, 0.6)
    focal = fill * min(width, height) * distance / radius
    principal = np.array([(width - 1) / 2, (height - 1) / 2])
    az = np.deg2rad(rng.uniform(az_lo, az_hi))
    el = np.deg2rad(rng.uniform(el_lo, el_hi))
    roll = np.deg2rad(rng.uniform(-3, 3))
    R1, C1 = _look_at(target, az, el, distance, roll)
    sign = 1.0 if rng.uniform() < 0.5 else -1.0
    daz = np.deg2rad(sign * baseline * rng.uniform(0.8, 1.2))
    del_ = np.deg2rad(rng.uniform(-0.3, 0.3) * baseline)
    el2 = np.clip(el + del_, np.deg2rad(el_lo - 5), np.deg2rad(el_hi + 5))
    target2 = target + rng.uniform(-0.05, 0.05, 3) * radius
    scale2 = rng.uniform(0.9, 1.1)
    R2, C2 = _look_at(target2, az + daz, el2, distance * scale2, np.deg2rad(rng.uniform(-4, 4)))
    cams = tuple(
        Camera(kind=kind, rotation=R, centre=C, focal=focal, principal=principal,
               reference_depth=distance * s)
        for R, C, s in ((R1, C1, 1.0), (R2, C2, scale2))
    )
    return cams  # type: ignore[return-value]


# --------------------------------------------------------------------------------------------
# Textures and shading
# --------------------------------------------------------------------------------------------

_PALETTE = {
    # material: (dark BGR, light BGR), albedo in [0, 1]
    "ground": ((0.25, 0.30, 0.30), (0.55, 0.62, 0.60)),
    "crate": ((0.10, 0.25, 0.40), (0.45, 0.65, 0.85)),
    "wall": ((0.15, 0.20, 0.45), (0.60, 0.70, 0.85)),
    "roof": ((0.10, 0.10, 0.25), (0.35, 0.40, 0.60)),
    "top": ((0.30, 0.30, 0.30), (0.75, 0.75, 0.72)),
    "page": ((0.10, 0.10, 0.10), (0.92, 0.90, 0.88)),
    "stripes": ((0.35, 0.15, 0.10), (0.85, 0.75, 0.60)),
    "tiles": ((0.18, 0.20, 0.24), (0.82, 0.84, 0.82)),
}


def _noise(rng: np.random.Generator, a: np.ndarray, b: np.ndarray, cell: float,
           lo: np.ndarray, hi: np.ndarray, stretch: float = 1.0) -> np.ndarray:
    """Smooth value noise (cubic B-spline of a random lattice), zero mean, std ~ 0.4."""
    ca, cb = cell * stretch, cell
    shape = (int(np.ceil((hi[1] - lo[1]) / cb)) + 5, int(np.ceil((hi[0] - lo[0]) / ca)) + 5)
    lattice = rng.standard_normal(shape)
    coords = np.stack([(b - lo[1]) / cb + 2.0, (a - lo[0]) / ca + 2.0])
    return ndimage.map_coordinates(lattice, coords, order=3, mode="nearest", prefilter=False)


def _band(t: np.ndarray, width: float) -> np.ndarray:
    """1 inside the band ``|t| < width`` (t already folded), 0 outside."""
    return (np.abs(t) < width).astype(np.float64)


def _texture(material: str, seed: int, outline: np.ndarray, a: np.ndarray,
             b: np.ndarray, unit: float = 1.0) -> np.ndarray:
    """Albedo (N, 3) BGR in [0, 1] of a polygon's texture at plane coordinates (a, b).

    ``unit`` is the world size of one pixel of a 640x480 view of the scene; only ``tiles`` uses
    it (its period is set in pixels); the other textures are in world units.
    """
    rng = np.random.default_rng(seed)
    lo, hi = outline.min(axis=0) - 1.0, outline.max(axis=0) + 1.0
    dark, light = (np.array(c) for c in _PALETTE[material])
    tint = rng.uniform(0.8, 1.2, 3)
    dark, light = np.clip(dark * tint, 0, 1), np.clip(light * tint, 0, 1)
    fine = _noise(rng, a, b, 0.18, lo, hi)
    mid = _noise(rng, a, b, 0.6, lo, hi)
    coarse = _noise(rng, a, b, 2.0, lo, hi)
    if material == "ground":
        p = 0.5 + 0.25 * coarse + 0.2 * mid + 0.15 * fine
        step = rng.uniform(2.0, 3.0)
        line = _band((a % step) - step / 2, 0.06) + _band(
            (b % step) - step / 2, 0.06)
        p = np.where(line > 0, 0.25 + 0.1 * fine, p)
    elif material == "crate":
        plank = rng.uniform(0.4, 0.6)
        row = np.floor(b / plank)
        shade = rng.uniform(0.3, 0.8, 64)[row.astype(np.int64) % 64]
        grain = _noise(rng, a, b, 0.08, lo, hi, stretch=12.0)
        p = shade + 0.25 * grain + 0.1 * mid
        p = np.where((b % plank) < 0.05, 0.08, p)
    elif material == "wall":
        bh, bl = 0.25, rng.uniform(0.5, 0.7)
        row = np.floor(b / bh)
        shift = (row % 2) * bl / 2
        col = np.floor((a + shift) / bl)
        table = rng.uniform(0.35, 0.75, (64, 64))
        p = table[row.astype(np.int64) % 64, col.astype(np.int64) % 64] + 0.12 * fine
        mortar = ((b % bh) < 0.035) | (((a + shift) % bl) < 0.035)
        p = np.where(mortar, 0.85 + 0.05 * fine, p)
        # Windows on a regular grid.
        sa, sb = rng.uniform(1.8, 2.6), rng.uniform(2.2, 2.8)
        wa, wb = 0.45 * sa, 0.5 * sb
        ua = (a - rng.uniform(0, sa)) % sa
        ub = (b - 0.8) % sb
        window = (ua < wa) & (ub < wb) & (b > 0.5)
        frame = window & ((ua < 0.08) | (ua > wa - 0.08) | (ub < 0.08) | (ub > wb - 0.08))
        glass = 0.12 + 0.15 * (ub / wb) + 0.08 * mid
        p = np.where(window, np.where(frame, 0.95, glass), p)
    elif material == "roof":
        th, tw = rng.uniform(0.25, 0.35), 0.4
        row = np.floor(b / th)
        shift = (row % 2) * tw / 2
        ramp = (b % th) / th
        p = 0.25 + 0.45 * ramp + 0.1 * mid + 0.08 * fine
        p = np.where(((a + shift) % tw) < 0.04, 0.1, p)
    elif material == "top":
        p = 0.55 + 0.2 * mid + 0.25 * fine + 0.15 * coarse
        step = rng.uniform(1.5, 2.5)
        p = np.where(_band((a % step) - step / 2, 0.05) > 0, 0.2, p)
    elif material == "tiles":
        # A checkerboard of square tiles 15-25 px wide at 640x480 (lattice vectors of 2 tiles
        # along the axes and 1 tile along each diagonal), thin grout joints, and a very weak
        # non-periodic component (about 1 % of the albedo range).
        tile = unit * rng.uniform(15.0, 25.0)
        ua = (a - rng.uniform(0.0, 2.0 * tile)) / tile
        ub = (b - rng.uniform(0.0, 2.0 * tile)) / tile
        light_tile = (np.floor(ua) + np.floor(ub)) % 2 == 0
        p = np.where(light_tile, 0.85, 0.15) + 0.02 * fine + 0.01 * mid
        joint = 0.05
        grout = ((ua % 1.0) < joint) | ((ub % 1.0) < joint)
        p = np.where(grout, 0.5 + 0.02 * fine, p)
    elif material == "stripes":
        period = rng.uniform(0.6, 1.0)
        phase = (a + rng.uniform(0.5, 1.5) * b) % period
        p = np.where(phase < period / 2, 0.75, 0.3) + 0.15 * mid + 0.1 * fine
    else:  # page: a poster of rectangles, text lines and noise
        p = 0.55 + 0.2 * mid + 0.15 * fine + 0.1 * coarse
        for _ in range(40):
            c = rng.uniform(lo, hi)
            half = rng.uniform(0.2, 1.4, 2)
            box = (np.abs(a - c[0]) < half[0]) & (np.abs(b - c[1]) < half[1])
            p = np.where(box, rng.uniform(0.05, 0.95) + 0.1 * fine, p)
        text = ((b % 0.3) < 0.12) & (_noise(rng, a, b, 0.15, lo, hi, stretch=2.0) > 0.15)
        p = np.where(text & (coarse > 0.1), 0.1, p)
    p = np.clip(p, 0.0, 1.0)[:, None]
    return dark + (light - dark) * p


def _tone_curves(rng: np.random.Generator, mode: Radiometric, n_faces: int) -> list:
    """Per-face callables mapping moving-view intensities (N, 3) in [0, 1] to [0, 1]."""
    curves = []
    for _ in range(n_faces):
        if mode == "monotone":
            gamma = np.exp(rng.uniform(np.log(0.5), np.log(2.0)))
            gain = rng.uniform(0.7, 1.2) * rng.uniform(0.9, 1.1, 3)
            off = rng.uniform(-0.05, 0.1)

            def curve(v, g=gamma, k=gain, o=off):
                return k * np.power(np.clip(v, 0, 1), g) + o
        elif mode == "nonmonotone":
            knots_x = np.linspace(0.0, 1.0, 5)
            knots_y = rng.uniform(0.1, 0.9, (3, 5))

            def curve(v, ky=knots_y, kx=knots_x):
                v = np.clip(v, 0, 1)
                return np.column_stack([np.interp(v[:, c], kx, ky[c]) for c in range(3)])
        else:
            def curve(v):
                return v
        curves.append(curve)
    return curves


def _light(rng: np.random.Generator) -> np.ndarray:
    az, el = rng.uniform(0, 2 * np.pi), np.deg2rad(rng.uniform(35, 70))
    return np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])


# --------------------------------------------------------------------------------------------
# Rendering
# --------------------------------------------------------------------------------------------


def _pixel_grid(size: tuple[int, int], ss: int) -> tuple[np.ndarray, np.ndarray]:
    width, height = size
    offsets = (np.arange(ss) - (ss - 1) / 2) / ss
    xs = (np.arange(width)[:, None] + offsets[None, :]).ravel()
    ys = (np.arange(height)[:, None] + offsets[None, :]).ravel()
    gx, gy = np.meshgrid(xs, ys)
    return gx.ravel(), gy.ravel()


def _render(
    camera: Camera,
    geometry: _Geometry,
    size: tuple[int, int],
    ss: int,
    shade: Callable[[int, np.ndarray, np.ndarray, np.ndarray], np.ndarray],
    sky: np.ndarray,
) -> np.ndarray:
    """Render an (H, W, 3) float BGR image with ``ss x ss`` supersampling."""
    width, height = size
    gx, gy = _pixel_grid(size, ss)
    poly, depth = _trace(camera, geometry, gx, gy)
    rgb = np.empty((len(gx), 3))
    rgb[:] = sky
    # A gentle vertical gradient on the sky, in image space.
    rgb *= (1.05 - 0.2 * gy / height)[:, None]
    for p in np.unique(poly[poly >= 0]):
        idx = np.flatnonzero(poly == p)
        a, b = _plane_coordinates(camera, geometry, int(p), gx[idx], gy[idx], depth[idx])
        rgb[idx] = shade(int(p), a, b, idx)
    img = rgb.reshape(height, ss, width, ss, 3).mean(axis=(1, 3))
    return img


def _finish(img: np.ndarray, color: ColorMode, blur: float, noise: float,
            rng: np.random.Generator) -> np.ndarray:
    """Blur, convert, add sensor noise (grey levels) and quantise to uint8."""
    img = img.astype(np.float32)
    if blur > 0:
        img = cv2.GaussianBlur(img, (0, 0), sigmaX=blur, sigmaY=blur,
                               borderType=cv2.BORDER_REFLECT)
    img = img.astype(np.float64) * 255.0
    if color == "gray":
        img = img @ _BGR_TO_GRAY
    if noise > 0:
        img = img + rng.normal(0.0, noise, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def _sample_points(
    rng: np.random.Generator,
    cams: tuple[Camera, Camera],
    geometry: _Geometry,
    polygons: tuple[Polygon, ...],
    face: np.ndarray,
    covisible: np.ndarray,
    size: tuple[int, int],
    n_interior: int,
    border: float,
) -> tuple[np.ndarray, np.ndarray]:
    """3-D conjugate points: covisible polyhedron corners, then face-interior points.

    Returns (N, 3) world points and (N,) plane ids (-1 for corners).
    """
    width, height = size
    ref, mov = cams

    def in_image(xy: np.ndarray) -> np.ndarray:
        return (
            (xy[:, 0] >= border) & (xy[:, 0] <= width - 1 - border)
            & (xy[:, 1] >= border) & (xy[:, 1] <= height - 1 - border)
        )

    def visible(cam: Camera, X: np.ndarray) -> np.ndarray:
        xy, z = project(cam, X)
        _, zhit = _trace(cam, geometry, xy[:, 0], xy[:, 1])
        tol = 1e-6 * cam.reference_depth
        return (z > 0) & in_image(xy) & (zhit >= z - tol)

    corners = np.unique(np.round(np.vstack([p.vertices for p in polygons]), 9), axis=0)
    corners = corners[visible(ref, corners) & visible(mov, corners)]
    world = [corners]
    plane = [np.full(len(corners), -1, dtype=np.int32)]

    if n_interior > 0:
        # Candidate pixels well inside a covisible face (3 px from any other plane).
        ok = np.zeros_like(covisible)
        for pid in np.unique(face[face >= 0]):
            ok |= ndimage.binary_erosion(face == pid, iterations=3, border_value=0)
        ok &= ndimage.binary_erosion(covisible, iterations=3, border_value=0)
        ys, xs = np.nonzero(ok)
        # Weighted random order (exponential race): each plane gets points in proportion to
        # the square root of its area, so that small faces are not left empty.
        area = np.bincount(face[ys, xs], minlength=int(face.max()) + 1).astype(np.float64)
        weight = 1.0 / np.sqrt(area[face[ys, xs]])
        order = np.argsort(rng.exponential(size=len(xs)) / weight, kind="stable")
        keep_xy = project(ref, corners)[0] if len(corners) else np.zeros((0, 2))
        spacing = 0.6 * np.sqrt(ok.sum() / max(n_interior, 1))
        spacing = max(spacing, 6.0)
        chosen: list[np.ndarray] = []
        for k in order:
            if len(chosen) >= n_interior:
                break
            xy = np.array([xs[k], ys[k]], dtype=np.float64) + rng.uniform(-0.5, 0.5, 2)
            if not in_image(xy[None])[0]:
                continue
            pts = np.vstack([keep_xy, *chosen]) if chosen else keep_xy
            if len(pts) and np.min(np.hypot(*(pts - xy).T)) < spacing:
                continue
            chosen.append(xy[None])
        if chosen:
            xy = np.vstack(chosen)
            p, z = _trace(ref, geometry, xy[:, 0], xy[:, 1])
            o, d = _rays(ref, xy[:, 0], xy[:, 1])
            X = o + z[:, None] * d
            good = (p >= 0) & visible(mov, np.where((p >= 0)[:, None], X, 0.0))
            world.append(X[good])
            plane.append(np.array([polygons[i].plane for i in p[good]], dtype=np.int32))
    return np.vstack(world), np.concatenate(plane)


def _dedupe(xy: np.ndarray, min_distance: float) -> np.ndarray:
    """Indices of points kept so that no two are closer than ``min_distance`` (first wins)."""
    kept: list[int] = []
    for i in range(len(xy)):
        if kept and np.min(np.hypot(*(xy[kept] - xy[i]).T)) < min_distance:
            continue
        kept.append(i)
    return np.array(kept, dtype=np.intp)


def _covisibility(
    camera: Camera, geometry: _Geometry, X: np.ndarray, seen: np.ndarray, size: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Project the seen points ``X`` (N, 3) into ``camera``: (xy, depth, covisible flags)."""
    width, height = size
    xy2, z2 = project(camera, X)
    inside = (
        seen & (xy2[:, 0] >= 0) & (xy2[:, 0] <= width - 1)
        & (xy2[:, 1] >= 0) & (xy2[:, 1] <= height - 1) & (z2 > 0)
    )
    _, zhit = _trace(camera, geometry, np.where(inside, xy2[:, 0], -10.0),
                     np.where(inside, xy2[:, 1], -10.0))
    covis = inside & (zhit >= z2 - 1e-6 * camera.reference_depth)
    return xy2, z2, covis


def _shift_for_overlap(
    rng: np.random.Generator,
    camera: Camera,
    geometry: _Geometry,
    X: np.ndarray,
    size: tuple[int, int],
    overlap: float,
) -> tuple[Camera, float]:
    """Move ``camera`` sideways until about ``overlap`` of the points ``X`` (N, 3) stay covisible.

    The camera centre moves in its image plane, in a direction within 30 degrees of its x axis
    (either way), by the amount found by bisection on a subsample of ``X``. Returns the moved
    camera and the shift in pixels at its reference depth (0 when the views already overlap
    less than requested).
    """
    width, height = size
    phi = rng.uniform(-0.5, 0.5) + (np.pi if rng.uniform() < 0.5 else 0.0)
    direction = np.cos(phi) * camera.rotation[0] + np.sin(phi) * camera.rotation[1]
    sample = X[:: max(1, len(X) // 20000)]
    if len(sample) == 0:
        return camera, 0.0
    every = np.ones(len(sample), dtype=bool)
    scale = camera.focal / camera.reference_depth  # pixels per world unit

    def moved(t: float) -> Camera:
        return Camera(kind=camera.kind, rotation=camera.rotation,
                      centre=camera.centre + t * direction, focal=camera.focal,
                      principal=camera.principal, reference_depth=camera.reference_depth)

    def fraction(t: float) -> float:
        return float(_covisibility(moved(t), geometry, sample, every, size)[2].mean())

    if fraction(0.0) <= overlap:
        return camera, 0.0
    lo, hi = 0.0, float(np.hypot(width, height)) / scale
    if fraction(hi) > overlap:
        return moved(hi), hi * scale
    for _ in range(16):
        mid = (lo + hi) / 2
        if fraction(mid) > overlap:
            lo = mid
        else:
            hi = mid
    t = (lo + hi) / 2
    return moved(t), t * scale


def _stream(family: str, seed: int, purpose: str) -> np.random.Generator:
    """Independent random stream per (family, seed, purpose)."""
    key = zlib.crc32(f"{family}/{purpose}".encode())
    return np.random.default_rng([int(seed), key])


def make_scene(
    family: str,
    seed: int,
    size: tuple[int, int] = (640, 480),
    camera: CameraKind = "affine",
    radiometric: Radiometric = "lighting",
    noise: float = 2.0,
    blur: float = 0.0,
    color: ColorMode = "gray",
    point_noise: float = 0.3,
    n_interior: int = 30,
    baseline: float = 22.0,
    distance: float = 3.0,
    supersample: int = 3,
    overlap: float | None = None,
) -> Scene:
    """Render a synthetic polyhedral scene from two viewpoints, with exact ground truth.

    Parameters
    ----------
    family : str
        One of :data:`FAMILIES`: ``"plane"``, ``"box"``, ``"prism"``, ``"gable"``,
        ``"lshape"``, ``"open_book"``, ``"city"``, ``"checker"``, ``"checker_box"``,
        ``"occluder"`` (see the module docstring).
    seed : int
        Seed (>= 0); the same arguments give the same scene bit for bit.
    size : (int, int)
        Image ``(width, height)`` in pixels (both views).
    camera : {"affine", "perspective"}
        Projection model of both views. ``"affine"`` is the weak-perspective approximation the
        paper assumes (an affine map per scene plane, so a triangle with correct vertices on one
        plane registers exactly); ``"perspective"`` is a pinhole at ``distance`` scene radii
        (within one plane the truth is then a homography, not an affine map).
    radiometric : {"none", "lighting", "monotone", "nonmonotone"}
        Radiometric change applied to the moving view (see the module docstring).
    noise : float
        Standard deviation of the additive Gaussian sensor noise, grey levels (0-255 scale),
        drawn independently for each view.
    blur : float
        Standard deviation (pixels) of a Gaussian blur applied to both views after the
        supersampled rendering; 0 for none.
    color : {"gray", "bgr"}
        ``(H, W)`` grey or ``(H, W, 3)`` BGR images.
    point_noise : float
        Standard deviation (pixels) of the Gaussian noise added independently to each coordinate
        of the conjugate points in each image.
    n_interior : int
        Target number of face-interior conjugate points in addition to the visible corners
        (fewer when the covisible area is small).
    baseline : float
        Typical azimuth change between the views, degrees (each scene draws 0.8-1.2 times it).
    distance : float
        Camera distance from the scene centre, in scene radii (> 1.5). It sets the strength of
        perspective; the affine camera is scaled to give the same framing.
    supersample : int
        Rays per pixel along each axis (anti-aliasing).
    overlap : float or None
        None (default): the views are redrawn until at least 75 % of the reference view's
        scene pixels are covisible. A fraction in (0, 1]: wide baseline with partial overlap;
        the moving camera is also moved sideways (a random direction within 30 degrees of its
        x axis, a separate random stream) so that about this fraction of them is covisible,
        and the views are redrawn until the achieved fraction is within 0.1 of it (after 20
        draws the last one is kept). ``info["covisible_fraction"]`` is the achieved fraction,
        ``info["overlap_requested"]`` this argument, ``info["overlap_shift_px"]`` the shift.

    Returns
    -------
    Scene

    Raises
    ------
    ValueError
        Unknown family or option, or a non-positive size.

    See Also
    --------
    make_unrelated_pair : two views of unrelated scenes (no correspondence at all).
    """
    if family not in FAMILIES:
        raise ValueError(f"unknown scene family {family!r}; expected one of {FAMILIES}")
    if camera not in ("affine", "perspective"):
        raise ValueError(f"camera must be 'affine' or 'perspective', got {camera!r}")
    if radiometric not in ("none", "lighting", "monotone", "nonmonotone"):
        raise ValueError(f"unknown radiometric change {radiometric!r}")
    if color not in ("gray", "bgr"):
        raise ValueError(f"color must be 'gray' or 'bgr', got {color!r}")
    width, height = int(size[0]), int(size[1])
    if width < 8 or height < 8 or supersample < 1:
        raise ValueError("size must be at least 8x8 pixels and supersample >= 1")
    if not distance > 1.5:
        raise ValueError("distance must be > 1.5 scene radii")
    if overlap is not None and not 0.0 < overlap <= 1.0:
        raise ValueError(f"overlap must be None or in (0, 1], got {overlap!r}")
    size = (width, height)

    # Geometry.
    faces, grounded = _family_faces(family, _stream(family, seed, "geometry"))
    allv = np.vstack([f.vertices for f in faces])
    lo, hi = allv.min(axis=0), allv.max(axis=0)
    target = (lo + hi) / 2
    radius = 0.5 * float(np.linalg.norm(hi - lo))
    if grounded:
        target[2] = _TARGET_HEIGHT.get(family, 0.35) * hi[2]
        faces = [_ground(target, radius, _GROUND_MATERIAL.get(family, "ground")), *faces]
    planes, plane_of = _merge_planes(faces)
    polygons = tuple(
        Polygon(vertices=np.asarray(f.vertices, dtype=np.float64), plane=plane_of[i],
                name=f.name, material=f.material)
        for i, f in enumerate(faces)
    )
    geometry = _geometry(polygons)

    # Cameras: redraw the moving view until the pair is well posed.
    cam_rng = _stream(family, seed, "cameras")
    shift_rng = _stream(family, seed, "overlap")  # used only when an overlap is requested
    gx, gy = _pixel_grid(size, 1)
    shift_px = 0.0
    for _attempt in range(20):
        cams = _cameras(cam_rng, family, camera, target, radius, size, baseline, distance)
        ref, mov = cams
        poly_ref, z_ref = _trace(ref, geometry, gx, gy)
        seen = poly_ref >= 0
        o, d = _rays(ref, gx, gy)
        X = o + np.where(seen, z_ref, 0.0)[:, None] * d
        if overlap is not None:
            mov, shift_px = _shift_for_overlap(shift_rng, mov, geometry, X[seen], size, overlap)
            cams = (ref, mov)
        xy2, z2, covis = _covisibility(mov, geometry, X, seen, size)
        if overlap is None:
            # Well posed: the scene fills most of the reference view and 75 % of it is covisible.
            if seen.mean() > 0.5 and covis.sum() > 0.75 * seen.sum():
                break
        elif seen.mean() > 0.5 and abs(covis.sum() / max(1, seen.sum()) - overlap) <= 0.1:
            break
    poly_mov, _ = _trace(mov, geometry, gx, gy)
    plane_ids = np.array([p.plane for p in polygons], dtype=np.int32)
    face = np.where(seen, plane_ids[poly_ref], -1).astype(np.int32).reshape(height, width)
    face_moving = np.where(poly_mov >= 0, plane_ids[poly_mov], -1).astype(np.int32)
    truth_x = np.where(seen, xy2[:, 0], np.nan).reshape(height, width)
    truth_y = np.where(seen, xy2[:, 1], np.nan).reshape(height, width)
    covisible = covis.reshape(height, width)

    # Shading: Lambert with a shading normal that faces the reference camera for open sheets.
    rad_rng = _stream(family, seed, "radiometry")
    light1 = _light(rad_rng)
    light2 = _light(rad_rng) if radiometric != "none" else light1
    exposure = rad_rng.uniform(0.75, 1.25) if radiometric != "none" else 1.0
    gamma = np.exp(rad_rng.uniform(-0.2, 0.2)) if radiometric != "none" else 1.0
    curves = _tone_curves(rad_rng, radiometric, len(polygons))
    ambient = 0.35
    view_dir = ref.centre - target
    normals = geometry.normal.copy()
    for i, poly in enumerate(polygons):
        sheet = poly.material in ("page", "ground")
        if sheet and normals[i] @ view_dir < 0:
            normals[i] = -normals[i]
    tex_rng = _stream(family, seed, "texture")
    tex_seeds = tex_rng.integers(0, 2**31, len(polygons))
    unit = radius / (_FILL.get(family, 0.6) * 480.0)  # world size of a pixel at 640x480
    sky = np.array([0.92, 0.80, 0.65]) * rad_rng.uniform(0.85, 1.0)

    def shader(light: np.ndarray, moving: bool) -> Callable:
        def shade(p: int, a: np.ndarray, b: np.ndarray, idx: np.ndarray) -> np.ndarray:
            albedo = _texture(polygons[p].material, int(tex_seeds[p]), geometry.outline[p], a, b,
                              unit=unit)
            lam = ambient + (1 - ambient) * max(0.0, float(normals[p] @ light))
            value = albedo * lam
            if moving and radiometric != "none":
                value = np.power(np.clip(value * exposure, 0, 1), gamma)
                value = curves[p](value)
            return np.clip(value, 0.0, 1.0)

        return shade

    img_rng = _stream(family, seed, f"noise{width}x{height}")
    reference = _finish(_render(ref, geometry, size, supersample, shader(light1, False), sky),
                        color, blur, noise, img_rng)
    moving = _finish(_render(mov, geometry, size, supersample, shader(light2, True), sky * 0.95),
                     color, blur, noise, img_rng)

    # Conjugate points.
    pt_rng = _stream(family, seed, f"points{width}x{height}")
    world, pplane = _sample_points(pt_rng, cams, geometry, polygons, face, covisible, size,
                                   n_interior, border=1.0)
    ref_xy, _ = project(ref, world)
    keep = _dedupe(ref_xy, 3.0)
    world, pplane, ref_xy = world[keep], pplane[keep], ref_xy[keep]
    mov_xy, _ = project(mov, world)
    keep = _dedupe(mov_xy, 3.0)
    world, pplane, ref_xy, mov_xy = world[keep], pplane[keep], ref_xy[keep], mov_xy[keep]
    ref_noisy = ref_xy + pt_rng.normal(0.0, point_noise, ref_xy.shape) if point_noise else ref_xy
    mov_noisy = mov_xy + pt_rng.normal(0.0, point_noise, mov_xy.shape) if point_noise else mov_xy

    return Scene(
        family=family,
        seed=int(seed),
        camera_kind=camera,
        radiometric=radiometric,
        reference=reference,
        moving=moving,
        face=face,
        truth_x=truth_x,
        truth_y=truth_y,
        covisible=covisible,
        face_moving=face_moving.reshape(height, width),
        planes=planes,
        polygons=polygons,
        cameras=cams,
        points_reference=ref_noisy,
        points_moving=mov_noisy,
        points_reference_exact=ref_xy,
        points_moving_exact=mov_xy,
        points_world=world,
        points_plane=pplane,
        info={
            "size": size,
            "noise": noise,
            "blur": blur,
            "color": color,
            "point_noise": point_noise,
            "baseline_deg": baseline,
            "distance_radii": distance,
            "scene_radius": radius,
            "covisible_fraction": float(covisible.sum() / max(1, (face >= 0).sum())),
            "overlap_requested": overlap,
            "overlap_shift_px": float(shift_px),
            "unrelated": False,
        },
    )


# Default families of make_unrelated_pair: not two tiled grounds (a periodic pattern makes any
# two tiled views look alike; pass ``families`` explicitly for that harder negative).
_UNRELATED_FAMILIES: tuple[str, ...] = tuple(f for f in FAMILIES if f not in ("checker",
                                                                               "checker_box"))


def make_unrelated_pair(
    seed: int,
    size: tuple[int, int] = (640, 480),
    families: tuple[str, str] | None = None,
    **kwargs,
) -> Scene:
    """Two views of two unrelated scenes: a negative case in which no pixel corresponds.

    The reference image is the reference view of one scene and the moving image the moving view
    of another scene (another family, another seed), both rendered by :func:`make_scene` with
    the same options, so both images look like ordinary scene views but nothing in one is seen
    in the other. A matcher should find no confident match, and a registration verdict should
    reject any registration of the pair.

    Parameters
    ----------
    seed : int
        Seed (>= 0): it is the reference scene's seed and also draws the families (unless
        given) and the moving scene's seed, which always differs from ``seed``. The same
        arguments give the same pair bit for bit.
    size : (int, int)
        Image ``(width, height)`` in pixels.
    families : (str, str) or None
        Families of the reference and of the moving scene; by default two different families
        drawn from :data:`FAMILIES` except ``"checker"`` and ``"checker_box"``.
    **kwargs
        Other options of :func:`make_scene` (``camera``, ``radiometric``, ``noise``, ``blur``,
        ``color``...), applied to both scenes.

    Returns
    -------
    Scene
        ``family`` is ``"unrelated"`` and ``seed`` is ``seed``. ``reference``, ``face``,
        ``planes``, ``polygons`` and the reference camera are those of the reference scene;
        ``moving`` and the moving camera come from the other scene (a different world frame:
        do not project the reference scene into it). ``truth_x`` and ``truth_y`` are NaN
        everywhere, ``covisible`` is all False, ``face_moving`` is -1 everywhere (the moving
        view sees none of :attr:`Scene.planes`), the point arrays are empty (shapes (0, 2),
        (0, 3) and (0,)). ``info`` is the reference scene's, with ``covisible_fraction`` 0,
        ``unrelated`` True, and ``reference_family``, ``moving_family``, ``reference_seed``,
        ``moving_seed``.

    Notes
    -----
    Renders two full scenes: about twice the time of :func:`make_scene`.

    Examples
    --------
    >>> s = make_unrelated_pair(0, size=(160, 120))  # doctest: +SKIP
    >>> s.info["unrelated"], bool(s.covisible.any()), s.points_reference.shape  # doctest: +SKIP
    (True, False, (0, 2))
    """
    rng = _stream("unrelated", seed, "pair")
    pool = _UNRELATED_FAMILIES
    first, second = rng.choice(len(pool), 2, replace=False)
    moving_seed = int(rng.integers(0, 2**31 - 1))
    if moving_seed == int(seed):
        moving_seed += 1
    if families is None:
        reference_family, moving_family = pool[int(first)], pool[int(second)]
    else:
        reference_family, moving_family = families
    a = make_scene(reference_family, seed, size=size, **kwargs)
    b = make_scene(moving_family, moving_seed, size=size, **kwargs)
    shape = a.shape
    nan = np.full(shape, np.nan)
    info = dict(a.info)
    info.update(
        covisible_fraction=0.0,
        unrelated=True,
        reference_family=reference_family,
        moving_family=moving_family,
        reference_seed=int(seed),
        moving_seed=moving_seed,
    )
    return Scene(
        family="unrelated",
        seed=int(seed),
        camera_kind=a.camera_kind,
        radiometric=a.radiometric,
        reference=a.reference,
        moving=b.moving,
        face=a.face,
        truth_x=nan,
        truth_y=nan.copy(),
        covisible=np.zeros(shape, dtype=bool),
        face_moving=np.full(shape, -1, dtype=np.int32),
        planes=a.planes,
        polygons=a.polygons,
        cameras=(a.cameras[0], b.cameras[1]),
        points_reference=np.zeros((0, 2)),
        points_moving=np.zeros((0, 2)),
        points_reference_exact=np.zeros((0, 2)),
        points_moving_exact=np.zeros((0, 2)),
        points_world=np.zeros((0, 3)),
        points_plane=np.zeros(0, dtype=np.int32),
        info=info,
    )
