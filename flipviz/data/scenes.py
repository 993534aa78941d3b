"""Procedural built-in objects (trimesh), centred at the origin inside about [-1.2, 1.2]^3, z up.

Symmetric scenes are built from parts on one side of their plane plus the exact reflections of
those parts, and of parts that are symmetric by construction (boxes centred on the plane), so
their GEOMETRY is exactly mirror-symmetric. Their COLOURS are not (a cushion patch, a stripe, a
differently coloured armrest on one side), and the renderer lights them from one side: as the
paper stresses, a mirrored image of a symmetric object is still not a view of the real object.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import cache

import numpy as np
import trimesh

from flipviz.data.dataset import DatasetError, Plane

Color = tuple[int, int, int]


@dataclass
class Part:
    """A piece of a scene: geometry with one colour per face (uint8 RGB)."""

    vertices: np.ndarray  # (V, 3) float64
    faces: np.ndarray  # (F, 3) int64
    colors: np.ndarray  # (F, 3) uint8

    @classmethod
    def of(cls, mesh: trimesh.Trimesh, color: Color) -> Part:
        faces = np.asarray(mesh.faces, dtype=np.int64)
        return cls(np.asarray(mesh.vertices, dtype=np.float64), faces, np.tile(np.uint8(color), (len(faces), 1)))

    def translated(self, t) -> Part:
        return Part(self.vertices + np.asarray(t, dtype=np.float64), self.faces, self.colors)

    def recolored(self, color: Color) -> Part:
        return Part(self.vertices, self.faces, np.tile(np.uint8(color), (len(self.faces), 1)))

    def mirrored(self, axis: int) -> Part:
        """Reflection through the plane {x_axis = 0}; face winding reversed to keep normals outward."""
        v = self.vertices.copy()
        v[:, axis] = -v[:, axis]  # negation is exact, so the reflection is bit-exact
        return Part(v, self.faces[:, ::-1].copy(), self.colors.copy())

    def subdivided(self, times: int = 1) -> Part:
        """Split each triangle into four (midpoints are exact under reflection); colours follow."""
        v, f, c = self.vertices, self.faces, self.colors
        for _ in range(times):
            v, f = trimesh.remesh.subdivide(v, f)
            c = np.repeat(c, 4, axis=0)  # trimesh puts the 4 children of face i at rows 4i..4i+3
        return Part(np.asarray(v, dtype=np.float64), np.asarray(f, dtype=np.int64), c)

    def paint(self, where: Callable[[np.ndarray], np.ndarray], color: Color) -> Part:
        """Recolour the faces whose centroids satisfy `where(centroids) -> bool mask`."""
        c = self.colors.copy()
        c[where(self.vertices[self.faces].mean(axis=1))] = color
        return Part(self.vertices, self.faces, c)


def box(extents: tuple[float, float, float], center: tuple[float, float, float], color: Color) -> Part:
    m = trimesh.creation.box(extents=extents)
    return Part.of(m, color).translated(center)


def centred_box(extents, center, color: Color, axis: int, subdivide: int = 0) -> list[Part]:
    """A box centred on the plane {x_axis = 0}, made of a half box and its exact reflection.

    (A plain box's triangulation is not mirror-symmetric: the diagonals of its faces flip.)
    """
    if center[axis] != 0:
        raise ValueError("centred_box: the box must be centred on the mirror plane")
    e, c = list(extents), list(center)
    e[axis] /= 2.0
    c[axis] = e[axis] / 2.0
    half = box(tuple(e), tuple(c), color).subdivided(subdivide)
    return [half, half.mirrored(axis)]


def cylinder(p0, p1, radius: float, color: Color, sections: int = 32) -> Part:
    return Part.of(
        trimesh.creation.cylinder(radius=radius, segment=np.array([p0, p1], dtype=float), sections=sections), color
    )


def sphere(center, radius: float, color: Color, subdivisions: int = 2) -> Part:
    return Part.of(trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius), color).translated(center)


def with_mirrors(parts: list[Part], axis: int) -> list[Part]:
    """`parts` (all on one side of the plane {x_axis = 0}) followed by their exact reflections."""
    return parts + [p.mirrored(axis) for p in parts]


def assemble(parts: list[Part]) -> trimesh.Trimesh:
    vs, fs, cs, offset = [], [], [], 0
    for p in parts:
        vs.append(p.vertices)
        fs.append(p.faces + offset)
        cs.append(p.colors)
        offset += len(p.vertices)
    colors = np.concatenate(cs)
    rgba = np.concatenate([colors, np.full((len(colors), 1), 255, np.uint8)], axis=1)
    return trimesh.Trimesh(np.concatenate(vs), np.concatenate(fs), face_colors=rgba, process=False)


# ---- the scenes --------------------------------------------------------------------------------

WOOD: Color = (150, 96, 52)
RED: Color = (190, 40, 40)
YELLOW: Color = (235, 200, 40)
GREEN: Color = (40, 130, 70)
BLUE: Color = (50, 90, 190)
GREY: Color = (120, 120, 125)
DARK: Color = (40, 40, 45)
WHITE: Color = (235, 235, 230)
ORANGE: Color = (240, 130, 30)


def chair() -> trimesh.Trimesh:
    """An armchair facing +y, mirror-symmetric about the plane x = 0."""
    side = [  # parts at x > 0; their reflections make the x < 0 side
        box((0.10, 0.10, 1.00), (0.45, 0.40, -0.56), WOOD),  # front leg
        box((0.10, 0.10, 1.00), (0.45, -0.40, -0.56), WOOD),  # back leg
        box((0.10, 0.10, 1.10), (0.45, -0.40, 0.49), WOOD),  # backrest post
        box((0.08, 0.05, 0.80), (0.22, -0.40, 0.50), WOOD),  # outer slat
        box((0.08, 0.70, 0.06), (0.52, 0.00, 0.38), WOOD),  # armrest
        box((0.06, 0.06, 0.36), (0.52, 0.30, 0.18), WOOD),  # armrest support
    ]
    parts = with_mirrors(side, axis=0)
    parts[len(side) + 4] = parts[len(side) + 4].recolored(GREEN)  # colour asymmetry: left armrest
    parts += centred_box((1.00, 0.90, 0.12), (0.0, 0.0, -0.06), WOOD, axis=0)  # seat
    parts += centred_box((1.00, 0.08, 0.18), (0.0, -0.40, 0.95), WOOD, axis=0)  # top rail
    parts += centred_box((0.08, 0.05, 0.80), (0.0, -0.40, 0.50), WOOD, axis=0)  # middle slat
    cushion = centred_box((0.84, 0.74, 0.08), (0.0, 0.02, 0.04), RED, axis=0, subdivide=3)
    yellow_patch = lambda c: (c[:, 0] > 0.1) & (c[:, 1] > 0.1) & (c[:, 2] > 0.07)  # noqa: E731 front-right only
    parts += [p.paint(yellow_patch, YELLOW) for p in cushion]
    return assemble(parts)


def truck() -> trimesh.Trimesh:
    """A toy truck driving along +x, mirror-symmetric about the plane y = 0."""
    side = [  # parts at y > 0
        cylinder((0.65, 0.42, -0.45), (0.65, 0.58, -0.45), 0.22, DARK),  # front wheel
        cylinder((-0.6, 0.42, -0.45), (-0.6, 0.58, -0.45), 0.22, DARK),  # rear wheel
        cylinder((0.65, 0.41, -0.45), (0.65, 0.59, -0.45), 0.10, GREY),  # hub caps
        cylinder((-0.6, 0.41, -0.45), (-0.6, 0.59, -0.45), 0.10, GREY),
        box((0.04, 0.16, 0.10), (0.92, 0.28, -0.12), WHITE),  # headlight
        box((0.12, 0.10, 0.06), (0.75, 0.46, 0.15), DARK),  # side mirror
    ]
    parts = with_mirrors(side, axis=1)
    parts[len(side) + 4] = parts[len(side) + 4].recolored(YELLOW)  # colour asymmetry: left headlight
    parts += centred_box((1.90, 0.80, 0.20), (0.0, 0.0, -0.30), GREY, axis=1)  # chassis
    parts += centred_box((0.60, 0.84, 0.56), (0.60, 0.0, 0.08), RED, axis=1)  # cabin
    parts += centred_box((0.02, 0.66, 0.26), (0.91, 0.0, 0.18), BLUE, axis=1)  # windscreen
    parts += centred_box((0.10, 0.84, 0.30), (0.92, 0.0, -0.17), RED, axis=1)  # bonnet front
    cargo = centred_box((1.10, 0.86, 0.66), (-0.38, 0.0, 0.13), YELLOW, axis=1, subdivide=3)
    stripe = lambda c: (c[:, 1] > 0.42) & (np.abs(c[:, 2] - 0.13) < 0.12)  # noqa: E731 on the +y side only
    parts += [p.paint(stripe, ORANGE) for p in cargo]
    return assemble(parts)


def mug() -> trimesh.Trimesh:
    """A mug with a handle on +x and a spoon leaning in it (no mirror symmetry)."""
    body = Part.of(trimesh.creation.annulus(r_min=0.47, r_max=0.55, height=1.2, sections=64), WHITE)
    body = body.translated((0, 0, -0.1)).paint(  # a blue band on one side
        lambda c: (np.arctan2(c[:, 1], c[:, 0]) > 1.6) & (np.arctan2(c[:, 1], c[:, 0]) < 2.8) & (c[:, 2] < 0.2), BLUE
    )
    handle = trimesh.creation.torus(major_radius=0.30, minor_radius=0.07, major_sections=48, minor_sections=16)
    handle.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (1, 0, 0)))
    parts = [
        body,
        Part.of(trimesh.creation.cylinder(radius=0.55, height=0.06, sections=64), WHITE).translated((0, 0, -0.67)),
        Part.of(trimesh.creation.cylinder(radius=0.47, height=0.02, sections=64), (90, 50, 25)).translated(
            (0, 0, 0.32)
        ),
        Part.of(handle, WHITE).translated((0.62, 0.0, -0.1)),
        cylinder((-0.12, 0.08, -0.2), (-0.48, 0.38, 0.95), 0.035, GREY, sections=12),  # spoon
        sphere((-0.48, 0.38, 0.95), 0.07, GREY, subdivisions=1),
    ]
    return assemble(parts)


def lamp() -> trimesh.Trimesh:
    """A desk lamp: round base, an arm going up and sideways, a tilted shade (no mirror symmetry)."""
    j1 = np.array([-0.25, -0.20, 0.45])  # elbow
    j2 = np.array([0.45, 0.30, 0.70])  # shade joint
    axis = np.array([0.35, 0.25, -1.0])
    axis /= np.linalg.norm(axis)
    h = 0.45
    shade = trimesh.creation.cone(radius=0.32, height=h, sections=48)
    # cone: base disc at z = 0, apex at z = h; turn it so the apex sits at j2, opening along `axis`
    R = trimesh.geometry.align_vectors([0, 0, -1], axis)
    shade.apply_transform(R)
    parts = [
        Part.of(trimesh.creation.cylinder(radius=0.5, height=0.1, sections=64), DARK).translated((-0.35, -0.25, -0.95)),
        box((0.14, 0.08, 0.06), (-0.05, -0.62, -0.87), RED),  # switch
        cylinder((-0.35, -0.25, -0.9), j1, 0.05, GREY),
        sphere(j1, 0.09, DARK),
        cylinder(j1, j2, 0.045, GREY),
        sphere(j2, 0.08, DARK),
        Part.of(shade, GREEN).translated(j2 + h * axis),
        sphere(j2 + 0.92 * h * axis, 0.11, YELLOW),  # bulb
    ]
    return assemble(parts)


@dataclass(frozen=True)
class SceneSpec:
    builder: Callable[[], trimesh.Trimesh]
    symmetry_plane: Plane | None
    description: str

    @property
    def symmetric(self) -> bool:
        return self.symmetry_plane is not None


BASE_SCENES: dict[str, SceneSpec] = {
    "chair": SceneSpec(
        chair, Plane(np.zeros(3), np.array([1.0, 0.0, 0.0])), "armchair, geometry symmetric about x = 0, colours not"
    ),
    "truck": SceneSpec(
        truck, Plane(np.zeros(3), np.array([0.0, 1.0, 0.0])), "toy truck, geometry symmetric about y = 0, colours not"
    ),
    "mug": SceneSpec(mug, None, "mug with a handle and a leaning spoon, asymmetric"),
    "lamp": SceneSpec(lamp, None, "desk lamp with a bent arm and tilted shade, asymmetric"),
}

# "<name>-turned": the object yawed and moved off the origin, so that no world axis is its plane
# and `official` (x = 0) is wrong. The true plane moves with it and stays known for measurement.
TURN_YAW_DEG = 35.0
TURN_OFFSET = (0.25, -0.15, 0.05)


def turn_transform() -> np.ndarray:
    """The 4x4 rigid transform of the turned scenes: yaw TURN_YAW_DEG about +z, then TURN_OFFSET."""
    T = trimesh.transformations.rotation_matrix(np.radians(TURN_YAW_DEG), (0.0, 0.0, 1.0))
    T[:3, 3] = TURN_OFFSET
    return T


def _turned(spec: SceneSpec) -> SceneSpec:
    T = turn_transform()

    def build() -> trimesh.Trimesh:
        mesh = spec.builder()
        mesh.apply_transform(T)
        return mesh

    plane = (
        None
        if spec.symmetry_plane is None
        else Plane(T[:3, :3] @ spec.symmetry_plane.point + T[:3, 3], T[:3, :3] @ spec.symmetry_plane.normal)
    )
    return SceneSpec(build, plane, f"{spec.description}; turned {TURN_YAW_DEG:g} deg and offset by {TURN_OFFSET}")


SCENES: dict[str, SceneSpec] = {**BASE_SCENES, **{f"{k}-turned": _turned(v) for k, v in BASE_SCENES.items()}}


def _spec(name: str) -> SceneSpec:
    if name not in SCENES:
        raise DatasetError(f"unknown built-in scene {name!r}; available: {', '.join(SCENES)}")
    return SCENES[name]


@cache
def cached_mesh(name: str) -> trimesh.Trimesh:
    return _spec(name).builder()


def build_mesh(name: str) -> trimesh.Trimesh:
    """The coloured mesh of built-in scene `name` (a fresh copy; face_colors set)."""
    return cached_mesh(name).copy()


def symmetry_plane(name: str) -> Plane | None:
    """The true mirror plane of the scene's geometry, None for asymmetric scenes."""
    return _spec(name).symmetry_plane
