"""A 3D digital twin of one frame (the paper's Fig. 6): measured points, fitted templates, cell, robot, gripper.

`TwinScene` is a flat list of coloured meshes and point clouds in the world frame (metres, z up). It exports to
GLB (glTF's y-up by a root node rotation, shading normals on every mesh; see `report.gltf`) and to a compact JSON
payload for the HTML viewer, which draws the z-up world directly.
"""

from __future__ import annotations

import base64
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from normpos_grasp.errors import InputError
from normpos_grasp.report.gltf import WORLD_FROM_GLTF, GltfMesh, GltfPoints, glb_bytes, linear_to_srgb
from normpos_grasp.typing import FloatArray, IntArray

Color = tuple[int, int, int]

PALETTE: tuple[Color, ...] = (
    (230, 25, 75),
    (60, 180, 75),
    (255, 225, 25),
    (0, 130, 200),
    (245, 130, 48),
    (145, 30, 180),
    (70, 240, 240),
    (240, 50, 230),
    (210, 245, 60),
    (250, 190, 212),
    (0, 128, 128),
    (170, 110, 40),
)


def palette_color(index: int) -> Color:
    """A distinct RGB colour for instance `index` (cycles after 12)."""
    return PALETTE[index % len(PALETTE)]


def capsule_mesh(radius: float, length: float, segments: int = 16, rings: int = 4) -> trimesh.Trimesh:
    """A closed capsule centred on its origin along z: hemisphere centres at z = -length/2 and +length/2 (the
    python-fcl convention of `kinematics.shapes`), poles at z = +-(length/2 + radius). Built here rather than by
    `trimesh.creation.capsule`, whose placement changed between trimesh versions. Metres.

    segments: vertices around the axis; rings: latitude steps per hemisphere (pole excluded).
    """
    if not (radius > 0 and length >= 0 and np.isfinite(radius) and np.isfinite(length)):
        raise InputError(f"capsule needs radius > 0 and length >= 0, got {radius}, {length}")
    if segments < 3 or rings < 1:
        raise InputError(f"capsule needs segments >= 3 and rings >= 1, got {segments}, {rings}")
    # latitudes from the top pole's first ring down to the bottom pole's last ring; each hemisphere ends at its equator
    lat_top = np.linspace(0.5 * np.pi, 0.0, rings + 1)[1:]
    lats = np.concatenate([lat_top, -lat_top[::-1]])
    centres = np.where(np.arange(len(lats)) < rings, 0.5 * length, -0.5 * length)
    theta = np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False)
    ring_xyz = np.stack(
        [
            radius * np.cos(lats)[:, None] * np.cos(theta)[None],
            radius * np.cos(lats)[:, None] * np.sin(theta)[None],
            np.broadcast_to((centres + radius * np.sin(lats))[:, None], (len(lats), segments)),
        ],
        axis=-1,
    ).reshape(-1, 3)
    top, bottom = len(ring_xyz), len(ring_xyz) + 1
    verts = np.vstack([ring_xyz, [[0.0, 0.0, 0.5 * length + radius]], [[0.0, 0.0, -0.5 * length - radius]]])
    j = np.arange(segments)
    jn = (j + 1) % segments
    faces: list[IntArray] = [np.column_stack([np.full(segments, top), j, jn])]
    for r in range(len(lats) - 1):
        a, b = r * segments + j, r * segments + jn
        c, d = a + segments, b + segments
        faces += [np.column_stack([a, c, b]), np.column_stack([b, c, d])]
    last = (len(lats) - 1) * segments
    faces.append(np.column_stack([np.full(segments, bottom), last + jn, last + j]))
    return trimesh.Trimesh(verts, np.vstack(faces), process=False)


@dataclass
class TwinScene:
    """Coloured meshes and point clouds in the world frame."""

    meshes: list[tuple[str, trimesh.Trimesh, Color, float]] = field(default_factory=list)
    clouds: list[tuple[str, FloatArray, FloatArray]] = field(default_factory=list)

    def add_mesh(self, name: str, mesh: trimesh.Trimesh, color: Color, opacity: float = 1.0) -> None:
        """Add a mesh already placed in the world frame (metres)."""
        if len(mesh.faces) == 0:
            raise InputError(f"mesh {name!r} has no faces")
        self.meshes.append((name, mesh, color, float(opacity)))

    def add_posed_mesh(
        self, name: str, mesh: trimesh.Trimesh, world_from_mesh: FloatArray, color: Color, opacity: float = 1.0
    ) -> None:
        """Add a copy of `mesh` transformed by `world_from_mesh` (4, 4)."""
        placed = mesh.copy()
        placed.apply_transform(np.asarray(world_from_mesh, dtype=np.float64))
        self.add_mesh(name, placed, color, opacity)

    def add_box(
        self, name: str, world_from_box: FloatArray, size: FloatArray, color: Color, opacity: float = 1.0
    ) -> None:
        """Add a box of full extents `size` (3,) metres at `world_from_box`."""
        self.add_mesh(name, trimesh.creation.box(extents=size, transform=world_from_box), color, opacity)

    def add_capsule(
        self, name: str, world_from_capsule: FloatArray, radius: float, length: float, color: Color
    ) -> None:
        """Add a capsule centred on `world_from_capsule` along its z axis, `length` metres between the hemisphere
        centres (the `kinematics.shapes` convention)."""
        self.add_posed_mesh(name, capsule_mesh(radius, length), world_from_capsule, color)

    def add_points(self, name: str, points: FloatArray, colors: FloatArray | Color, max_points: int = 20000) -> None:
        """Add a point cloud (N, 3) with per-point (N, 3) uint8 colours or one colour; subsampled to `max_points`."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        cols = np.asarray(colors, dtype=np.float64)
        cols = np.broadcast_to(cols, pts.shape) if cols.ndim == 1 else cols.reshape(-1, 3)
        if len(pts) > max_points:
            keep = np.linspace(0, len(pts) - 1, max_points).astype(np.int64)
            pts, cols = pts[keep], cols[keep]
        self.clouds.append((name, pts, np.asarray(cols, dtype=np.float64)))

    def add_axes(self, name: str, world_from_frame: FloatArray, length: float = 0.05) -> None:
        """Add an RGB axis triad (x red, y green, z blue) as thin boxes."""
        for axis, color in zip(range(3), ((230, 30, 30), (30, 200, 30), (30, 60, 230)), strict=True):
            offset = np.eye(4)
            offset[axis, 3] = length / 2.0
            size = np.full(3, length * 0.08)
            size[axis] = length
            self.add_box(f"{name}_{'xyz'[axis]}", np.asarray(world_from_frame) @ offset, size, color)

    def bounds(self) -> FloatArray:
        """(2, 3) min and max corner of everything in the scene, metres."""
        parts = [m.bounds for _, m, _, _ in self.meshes] + [
            np.array([p.min(0), p.max(0)]) for _, p, _ in self.clouds if len(p)
        ]
        if not parts:
            return np.array([[-0.5, -0.5, 0.0], [0.5, 0.5, 0.5]])
        stacked = np.concatenate(parts)
        return np.array([stacked.min(0), stacked.max(0)])

    def to_trimesh_scene(self) -> trimesh.Scene:
        """The scene as a trimesh Scene in the z-up world frame (face colours; no glTF axis change)."""
        scene = trimesh.Scene()
        for name, mesh, color, opacity in self.meshes:
            coloured = mesh.copy()
            rgba = np.array([*color, round(255 * opacity)], dtype=np.uint8)
            coloured.visual = trimesh.visual.ColorVisuals(coloured, face_colors=np.tile(rgba, (len(mesh.faces), 1)))
            scene.add_geometry(coloured, node_name=name, geom_name=name)
        for name, pts, cols in self.clouds:
            if len(pts):
                rgba = np.column_stack([cols, np.full(len(pts), 255.0)]).astype(np.uint8)
                scene.add_geometry(trimesh.PointCloud(pts, colors=rgba), node_name=name, geom_name=name)
        return scene

    @classmethod
    def from_glb(cls, path: str | Path) -> TwinScene:
        """Read a GLB written by `export_glb` (or any glTF scene): meshes with their base colour and opacity, point
        clouds with their colours, placed by the scene graph and turned from glTF's y-up into the z-up world.

        Colours are read as the spec stores them (linear) and returned as sRGB; 8-bit rounding in trimesh's reader
        moves dark values by a few steps.
        """
        source = Path(path)
        try:
            loaded: Any = trimesh.load(source, force="scene")
        except (OSError, ValueError, KeyError) as exc:
            raise InputError(f"cannot read the 3D scene {source}: {exc}") from exc
        scene = cls()
        for node in loaded.graph.nodes_geometry:
            gltf_from_node, geom_name = loaded.graph[node]
            world_from_node = WORLD_FROM_GLTF @ np.asarray(gltf_from_node, dtype=np.float64)
            geom = loaded.geometry[geom_name]
            if isinstance(geom, trimesh.PointCloud):
                pts = trimesh.transform_points(np.asarray(geom.vertices), world_from_node)
                if len(geom.colors):
                    cols: FloatArray | Color = 255.0 * _srgb(np.asarray(geom.colors, dtype=np.float64)[:, :3])
                else:
                    cols = (200, 200, 200)
                scene.add_points(node, pts, cols, max_points=max(len(pts), 1))
            elif isinstance(geom, trimesh.Trimesh) and len(geom.faces):
                rgba = _main_rgba(geom)
                rgb = np.round(255.0 * _srgb(rgba[:3]))
                color = (int(rgb[0]), int(rgb[1]), int(rgb[2]))
                scene.add_posed_mesh(node, geom, world_from_node, color, float(rgba[3]) / 255.0)
        if not scene.meshes and not scene.clouds:
            raise InputError(f"{source} holds no meshes or point clouds")
        return scene

    def export_glb(self, path: str | Path) -> None:
        """Write the scene as binary glTF (GLB), y-up by its root node, with shading normals on every mesh;
        written to a temporary file and renamed."""
        from normpos_grasp import __version__

        meshes = [
            GltfMesh(name, np.asarray(m.vertices), np.asarray(m.faces), color, opacity)
            for name, m, color, opacity in self.meshes
        ]
        clouds = [GltfPoints(name, pts, cols) for name, pts, cols in self.clouds]
        target = Path(path)
        tmp = target.with_name(target.name + ".tmp")
        tmp.write_bytes(glb_bytes(meshes, clouds, generator=f"normpos-grasp {__version__}"))
        tmp.replace(target)

    def to_payload(self) -> dict[str, Any]:
        """JSON-ready description for the HTML viewer: base64 little-endian float32/uint32 buffers."""
        meshes = []
        for name, mesh, color, opacity in self.meshes:
            meshes.append(
                {
                    "name": name,
                    "color": [c / 255.0 for c in color],
                    "opacity": opacity,
                    "positions": _b64(np.asarray(mesh.vertices, dtype="<f4")),
                    "indices": _b64(np.asarray(mesh.faces, dtype="<u4")),
                }
            )
        clouds = []
        for name, pts, cols in self.clouds:
            clouds.append(
                {
                    "name": name,
                    "positions": _b64(np.asarray(pts, dtype="<f4")),
                    "colors": _b64(np.asarray(cols / 255.0, dtype="<f4")),
                }
            )
        return {"meshes": meshes, "clouds": clouds, "bounds": self.bounds().tolist()}


def _srgb(linear_0_255: FloatArray) -> FloatArray:
    return linear_to_srgb(np.asarray(linear_0_255, dtype=np.float64) / 255.0)


def _main_rgba(mesh: trimesh.Trimesh) -> FloatArray:
    """(4,) RGBA 0..255 as stored in the file (linear): the PBR base colour, else the visual's main colour."""
    visual: Any = mesh.visual
    factor = getattr(getattr(visual, "material", None), "baseColorFactor", None)
    if factor is not None:
        return np.asarray(factor, dtype=np.float64).reshape(4)
    colour_visual = visual.to_color() if hasattr(visual, "to_color") else visual
    return np.asarray(colour_visual.main_color, dtype=np.float64).reshape(4)


def _b64(array: np.ndarray) -> str:
    return base64.b64encode(np.ascontiguousarray(array).tobytes()).decode("ascii")
