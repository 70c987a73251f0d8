"""Mesh validation and repair for CAD templates: watertight, outward normals, no degenerate faces, sane size."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from normpos_grasp.errors import MeshError

if TYPE_CHECKING:
    import trimesh

logger = logging.getLogger(__name__)

#: Plausible object sizes (largest extent, metres) for a pick-and-place cell.
MIN_SIZE_M = 0.002
MAX_SIZE_M = 2.0
#: above this many faces the (pure Python) winding repair is skipped and only reported
MAX_FACES_WINDING_FIX = 20000


@dataclass(frozen=True)
class MeshReport:
    """What `check_mesh` found and what it repaired.

    watertight / winding_consistent / outward: state after repair. degenerate_faces, duplicate_faces,
    unreferenced_vertices: counts removed. flipped: normals were inverted to point outward.
    size_m: largest extent (metres). problems: remaining defects (empty = usable). repairs: what was done.
    """

    name: str
    n_vertices: int
    n_faces: int
    watertight: bool
    winding_consistent: bool
    outward: bool
    degenerate_faces: int
    duplicate_faces: int
    flipped: bool
    size_m: float
    problems: tuple[str, ...]
    repairs: tuple[str, ...]

    @property
    def ok(self) -> bool:
        return not self.problems

    def summary(self) -> str:
        state = "ok" if self.ok else "problems: " + "; ".join(self.problems)
        fixed = ("; repaired: " + "; ".join(self.repairs)) if self.repairs else ""
        return (
            f"mesh '{self.name}': {self.n_vertices} vertices, {self.n_faces} faces, {self.size_m:.4f} m, {state}{fixed}"
        )


def check_mesh(
    mesh: trimesh.Trimesh,
    name: str = "mesh",
    *,
    repair: bool = True,
    require_watertight: bool = False,
) -> tuple[trimesh.Trimesh, MeshReport]:
    """Validate `mesh` (metres) and return a repaired copy with a report; the input is not modified.

    Repairs: degenerate and duplicate faces, unreferenced vertices, merged duplicate vertices, inconsistent
    winding, inward normals, small holes. Each repair is logged as a warning.

    Raises:
        MeshError: no faces, non-finite vertices, a size outside [2 mm, 2 m] (a unit mix-up), or, with
            `require_watertight`, a mesh that stays open after repair.
    """
    import trimesh

    if not isinstance(mesh, trimesh.Trimesh):
        raise MeshError(f"template '{name}': expected a trimesh.Trimesh, got {type(mesh).__name__}")
    if len(mesh.faces) == 0 or len(mesh.vertices) < 4:
        raise MeshError(f"template '{name}': mesh has {len(mesh.faces)} faces; a closed surface needs at least 4")
    if not np.all(np.isfinite(mesh.vertices)):
        raise MeshError(f"template '{name}': mesh has NaN or infinite vertices; re-export it from CAD")
    m = mesh.copy()
    repairs: list[str] = []
    n_faces0 = len(m.faces)
    if repair:
        m.merge_vertices()
        area_ok = m.area_faces > (1e-12 * max(float(m.scale), 1e-9) ** 2)
        nondeg = m.nondegenerate_faces() & area_ok
        n_deg = int((~nondeg).sum())
        if n_deg:
            m.update_faces(nondeg)
            repairs.append(f"removed {n_deg} degenerate faces")
        uniq = m.unique_faces()
        n_dup = int((~uniq).sum())
        if n_dup:
            m.update_faces(uniq)
            repairs.append(f"removed {n_dup} duplicate faces")
        n_v = len(m.vertices)
        m.remove_unreferenced_vertices()
        if len(m.vertices) != n_v:
            repairs.append(f"removed {n_v - len(m.vertices)} unreferenced vertices")
        if not m.is_winding_consistent:
            if len(m.faces) <= MAX_FACES_WINDING_FIX:
                fix_winding(m)
                repairs.append("made face winding consistent")
            else:
                logger.warning(
                    "mesh '%s': %d faces with inconsistent winding left as is (the fix is slow above %d faces); "
                    "the fitter orients its normals by ray casting",
                    name,
                    len(m.faces),
                    MAX_FACES_WINDING_FIX,
                )
        if not m.is_watertight:
            fill_small_holes(m)
            if m.is_watertight:
                repairs.append("filled holes")
    else:
        n_deg = int((~m.nondegenerate_faces()).sum())
        n_dup = int((~m.unique_faces()).sum())
    flipped = False
    outward = True
    if m.is_watertight and m.is_winding_consistent:
        vol = float(m.volume)
        if vol < 0:
            if repair:
                m.invert()
                flipped = True
                repairs.append("inverted inward-facing normals")
            else:
                outward = False
    size = float(np.max(m.extents)) if len(m.vertices) else 0.0
    problems: list[str] = []
    if len(m.faces) == 0:
        raise MeshError(f"template '{name}': all {n_faces0} faces are degenerate")
    if not m.is_watertight:
        problems.append("not watertight (open surface): volume, inside tests and mass are unreliable")
    if not m.is_winding_consistent:
        problems.append("inconsistent face winding")
    if not outward:
        problems.append("normals point inward")
    if not MIN_SIZE_M <= size <= MAX_SIZE_M:
        raise MeshError(
            f"template '{name}': mesh size {size:.6g} m lies outside [{MIN_SIZE_M}, {MAX_SIZE_M}] m; "
            "check the declared units (mm vs m)"
        )
    report = MeshReport(
        name=name,
        n_vertices=len(m.vertices),
        n_faces=len(m.faces),
        watertight=bool(m.is_watertight),
        winding_consistent=bool(m.is_winding_consistent),
        outward=outward,
        degenerate_faces=n_deg,
        duplicate_faces=n_dup,
        flipped=flipped,
        size_m=size,
        problems=tuple(problems),
        repairs=tuple(repairs),
    )
    if require_watertight and not report.watertight:
        raise MeshError(report.summary() + "; close the mesh in CAD or pass require_watertight=False")
    if repairs or problems:
        logger.warning("%s", report.summary())
    return m, report


# -- repairs (scipy graphs, no networkx: trimesh.repair needs networkx for these) ------------------------------
def fix_winding(mesh: trimesh.Trimesh) -> int:
    """Make the face winding consistent within each connected patch (in place); returns the faces flipped.

    Breadth-first over the face adjacency: a face whose shared edge with its (already fixed) parent runs in the
    same direction is reversed. The same rule as `trimesh.repair.fix_winding`, on scipy's graph routines.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import breadth_first_order, connected_components

    faces = np.asarray(mesh.faces, dtype=np.int64).copy()
    n = len(faces)
    adjacency = np.asarray(mesh.face_adjacency, dtype=np.int64).reshape(-1, 2)
    if n == 0 or len(adjacency) == 0:
        return 0
    ones = np.ones(len(adjacency), dtype=np.int8)
    graph = coo_matrix((ones, (adjacency[:, 0], adjacency[:, 1])), shape=(n, n)).tocsr()
    _, labels = connected_components(graph, directed=False)
    _, first = np.unique(labels, return_index=True)
    flipped = 0
    for start in first:
        order, parent = breadth_first_order(graph, int(start), directed=False, return_predecessors=True)
        for f in order[1:]:
            a, b = faces[parent[f]], faces[f]
            a_edges = {(int(a[0]), int(a[1])), (int(a[1]), int(a[2])), (int(a[2]), int(a[0]))}
            if any((int(b[i]), int(b[(i + 1) % 3])) in a_edges for i in range(3)):
                faces[f] = b[::-1]
                flipped += 1
    if flipped:
        mesh.faces = faces
    return flipped


def fill_small_holes(mesh: trimesh.Trimesh) -> int:
    """Close boundary loops of 3 or 4 vertices with triangles wound like their neighbours (in place).

    Returns the number of holes filled; larger holes are left open (as `trimesh.repair.fill_holes` does).
    """
    from trimesh.grouping import group_rows

    boundary_rows = group_rows(mesh.edges_sorted, require_count=1)
    if len(boundary_rows) < 3:
        return 0
    edges = np.asarray(mesh.edges, dtype=np.int64)[boundary_rows]  # directed as in their faces
    nxt: dict[int, int] = {}
    ambiguous: set[int] = set()
    for u, v in edges:
        if int(u) in nxt:
            ambiguous.add(int(u))
        nxt[int(u)] = int(v)
    new_faces: list[list[int]] = []
    seen: set[int] = set()
    for start in list(nxt):
        if start in seen:
            continue
        loop = [start]
        seen.add(start)
        node = nxt[start]
        while node != start and node in nxt and node not in seen and len(loop) <= 4:
            loop.append(node)
            seen.add(node)
            node = nxt[node]
        if node != start or len(loop) not in (3, 4) or ambiguous.intersection(loop):
            continue
        # the hole's faces run against the boundary's direction: reverse the loop
        c = loop[::-1]
        new_faces.extend([c[0], c[i], c[i + 1]] for i in range(1, len(c) - 1))
    if not new_faces:
        return 0
    mesh.faces = np.vstack([np.asarray(mesh.faces, dtype=np.int64), np.asarray(new_faces, dtype=np.int64)])
    return len(new_faces)
