"""Automatic grasp synthesis per object shape, in the object frame, as `GraspAnnotation`s.

Schemes: box (parallel across each face pair from every side, also tilted about the closing axis and slid along
long sides; suction on each face), cylinder (side grasps around the axis, also leaning along it, top-down across
the diameter, across the caps, suction on caps), sphere (parallel from sampled directions, suction), plate (suction
on the broad faces, edge pinch, pinch across width or length from the face), ring (pinches across the outer
diameter and the faces, plus the antipodal pairs), irregular / bracket (antipodal pairs with a friction-cone test,
suction on flat facets). TCP convention: z = approach (into the object), x = jaw
closing direction. Which faces are exposed is decided later by the collision checks, not here.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from normpos_grasp.records.template import GraspAnnotation, Template
from normpos_grasp.typing import FloatArray


@dataclass(frozen=True)
class SynthesisOptions:
    """Settings of automatic synthesis.

    clearance_m: jaw opening beyond the object width on each side, m. max_grip_depth_m: deepest the TCP goes below
    the approached face, m. cup_diameter_m: suction cup diameter (faces smaller than this get no suction grasp), m.
    side_angles: approach directions around a cylinder / sphere. friction_coef: Coulomb mu of the antipodal test.
    antipodal_samples: surface samples for irregular parts. approach_m / retreat_m: straight-line lengths, m.
    seed: RNG seed for surface sampling (results are reproducible). finger_tip_m: how far the jaw tips reach past
    the TCP along the approach, m (set from the tool, so grasps do not push the tips through the part's far side).
    tilt_angles_rad: box pinches are also offered tilted by +- each angle about the closing axis (the jaws stay on
    the same faces; the hand leans away from a wall or a neighbour), rad. slide_min_m: a box (or flat plate) side
    at least this long along the jaw's width direction also gets pinches a quarter of its length off centre on
    both sides, m.
    """

    clearance_m: float = 0.01
    max_grip_depth_m: float = 0.025
    cup_diameter_m: float = 0.03
    side_angles: int = 8
    friction_coef: float = 0.4
    antipodal_samples: int = 64
    approach_m: float = 0.08
    retreat_m: float = 0.1
    seed: int = 0
    finger_tip_m: float = 0.0
    tilt_angles_rad: tuple[float, ...] = (0.35,)
    slide_min_m: float = 0.06

    def depth(self, extent: float) -> float:
        """TCP depth below the approached face for a part `extent` deep along the approach, m: at most half the
        part and `max_grip_depth_m`, and shallow enough that jaw tips reaching `finger_tip_m` past the TCP stop
        2 mm short of the far face (never under 30 % of the part)."""
        return float(max(min(extent / 2.0, self.max_grip_depth_m, extent - self.finger_tip_m - 0.002), 0.3 * extent))


def tcp_frame(approach: FloatArray, closing: FloatArray, position: FloatArray) -> FloatArray:
    """(4, 4) object_from_tcp with z along `approach`, x along `closing` (orthogonalised), origin `position`."""
    z = np.asarray(approach, dtype=np.float64)
    z = z / np.linalg.norm(z)
    x = np.asarray(closing, dtype=np.float64) - z * float(np.dot(closing, z))
    nx = np.linalg.norm(x)
    if nx < 1e-9:
        helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        x = helper - z * float(np.dot(helper, z))
        nx = np.linalg.norm(x)
    x = x / nx
    pose = np.eye(4)
    pose[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    pose[:3, 3] = position
    return pose


def _rot_x(angle: float) -> FloatArray:
    """(3, 3) rotation by `angle` rad about x (the TCP's closing axis)."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _perpendicular(axis: FloatArray) -> tuple[FloatArray, FloatArray]:
    helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(axis, helper)
    u /= np.linalg.norm(u)
    return u, np.cross(axis, u)


def synthesize(
    template: Template, kinds: tuple[str, ...] = ("parallel", "suction"), options: SynthesisOptions | None = None
) -> list[GraspAnnotation]:
    """Grasps for `template` by its `shape` class, for the tool kinds in `kinds` ('parallel', 'suction')."""
    opts = options or SynthesisOptions()
    shape = template.shape
    if shape in ("box",):
        out = _box(template, opts)
    elif shape == "cylinder":
        out = _cylinder(template, opts)
    elif shape == "sphere":
        out = _sphere(template, opts)
    elif shape == "plate":
        out = _plate(template, opts)
    elif shape == "ring":  # antipodal rim pinches, plus pinches across the outer diameter and across the faces
        outer = [g for g in _cylinder(template, opts) if g.id.startswith(("cyl_top", "cyl_caps"))]
        out = outer + _antipodal(template, opts) + _facet_suction(template, opts)
    else:  # irregular, bracket
        out = _antipodal(template, opts) + _facet_suction(template, opts)
    return [g for g in out if g.scheme in kinds]


def _obb(template: Template) -> tuple[FloatArray, FloatArray]:
    """object_from_box (4, 4) and full extents (3,) of the template's minimum-volume oriented box."""
    obb = template.mesh.bounding_box_oriented
    pose = np.asarray(obb.primitive.transform, dtype=np.float64).copy()
    ext = np.asarray(obb.primitive.extents, dtype=np.float64)
    # Prefer the object's own axes when the mesh is already axis-aligned (boxes modelled in their frame).
    aabb_ext = np.asarray(template.mesh.extents, dtype=np.float64)
    if np.prod(aabb_ext) <= np.prod(ext) * (1 + 1e-6):
        pose = np.eye(4)
        pose[:3, 3] = np.asarray(template.mesh.bounds, dtype=np.float64).mean(axis=0)
        ext = aabb_ext
    if np.linalg.det(pose[:3, :3]) < 0:
        pose[:3, 2] *= -1
    return pose, ext


def _tilted(gid: str, base: FloatArray, opening: float, quality: float, o: SynthesisOptions) -> list[GraspAnnotation]:
    """Parallel pinch `base` tilted by +- each of `o.tilt_angles_rad` about its closing axis (x), quality lowered by
    0.1 per radian; ids `<gid>_t+<deg>` / `<gid>_t-<deg>`."""
    out = []
    for ang in o.tilt_angles_rad:
        for sign in (1.0, -1.0):
            tilted = base.copy()
            tilted[:3, :3] = base[:3, :3] @ _rot_x(sign * ang)
            gid_t = f"{gid}_t{'+' if sign > 0 else '-'}{np.rad2deg(ang):.0f}"
            out.append(_g(gid_t, "parallel", tilted, opening, quality - 0.1 * ang, o))
    return out


def _g(
    gid: str,
    scheme: str,
    pose: FloatArray,
    opening: float,
    quality: float,
    o: SynthesisOptions,
    free_axis: FloatArray | None = None,
) -> GraspAnnotation:
    return GraspAnnotation(
        id=gid,
        scheme=scheme,
        object_from_tcp=pose,
        opening_m=float(opening),
        priority=float(quality),
        approach_m=o.approach_m,
        retreat_m=o.retreat_m,
        free_axis=free_axis,
    )


def _box(t: Template, o: SynthesisOptions) -> list[GraspAnnotation]:
    frame, ext = _obb(t)
    rot, c = frame[:3, :3], frame[:3, 3]
    out = []
    for i in range(3):  # closing axis
        for j in range(3):  # approach axis
            if i == j:
                continue
            k = 3 - i - j
            depth = o.depth(float(ext[j]))
            slides = [0.0] if ext[k] < o.slide_min_m else [0.0, -ext[k] / 4.0, ext[k] / 4.0]
            for s in (1.0, -1.0):
                approach = s * rot[:, j]
                quality = 0.6 + 0.4 * min(ext[k], 0.05) / 0.05 - 0.2 * ext[i] / max(ext.max(), 1e-9)
                for n_slide, slide in enumerate(slides):
                    pos = c - approach * (ext[j] / 2.0 - depth) + rot[:, k] * slide
                    base = tcp_frame(approach, rot[:, i], pos)
                    gid = f"box_pair_c{i}_a{j}{'+' if s > 0 else '-'}" + (f"_s{n_slide}" if n_slide else "")
                    q = quality - (0.1 if n_slide else 0.0)
                    out.append(_g(gid, "parallel", base, ext[i] + 2 * o.clearance_m, q, o))
                    out.extend(_tilted(gid, base, ext[i] + 2 * o.clearance_m, q, o))
    for j in range(3):
        others = [m for m in range(3) if m != j]
        if min(ext[others]) < o.cup_diameter_m:
            continue
        area = ext[others[0]] * ext[others[1]]
        for s in (1.0, -1.0):
            approach = s * rot[:, j]
            pos = c - approach * ext[j] / 2.0
            quality = 0.5 + 0.5 * min(area / 0.01, 1.0)
            for r_idx, closing in enumerate((rot[:, others[0]], rot[:, others[1]])):
                out.append(
                    _g(
                        f"box_suction_a{j}{'+' if s > 0 else '-'}_r{r_idx}",
                        "suction",
                        tcp_frame(approach, closing, pos),
                        0.0,
                        quality,
                        o,
                    )
                )
    return out


def _cylinder_axis(t: Template) -> tuple[FloatArray, FloatArray, float, float]:
    """(axis (3,), centre (3,), radius, length) of a cylinder template."""
    if t.symmetry.continuous:
        axis = np.asarray(t.symmetry.continuous[0][0], dtype=np.float64)
        axis = axis / np.linalg.norm(axis)
        v = np.asarray(t.mesh.vertices, dtype=np.float64)
        centre = np.asarray(t.mesh.bounds, dtype=np.float64).mean(axis=0)
        along = (v - centre) @ axis
        centre = centre + axis * (along.max() + along.min()) / 2.0
        along = (v - centre) @ axis
        radial = np.linalg.norm((v - centre) - np.outer(along, axis), axis=1)
        return axis, centre, float(radial.max()), float(along.max() - along.min())
    frame, ext = _obb(t)
    # axis: the extent that differs most from the other two (the two radial extents agree)
    diffs = [abs(ext[(i + 1) % 3] - ext[(i + 2) % 3]) for i in range(3)]
    i = int(np.argmin(diffs))
    return frame[:3, i], frame[:3, 3], float(max(ext[(i + 1) % 3], ext[(i + 2) % 3]) / 2.0), float(ext[i])


def _cylinder(t: Template, o: SynthesisOptions) -> list[GraspAnnotation]:
    axis, c, r, length = _cylinder_axis(t)
    u, v = _perpendicular(axis)
    out = []
    heights = [0.0] if length < max(4 * r, o.slide_min_m) else [-length / 4.0, 0.0, length / 4.0]
    for k in range(o.side_angles):
        ang = 2 * np.pi * k / o.side_angles
        approach = -(np.cos(ang) * u + np.sin(ang) * v)
        closing = np.cross(axis, approach)
        depth = o.depth(2 * r)
        for h_idx, h in enumerate(heights):
            pos = c + h * axis - approach * (r - depth)
            base = tcp_frame(approach, closing, pos)
            gid = f"cyl_side_{k}_h{h_idx}"
            out.append(_g(gid, "parallel", base, 2 * r + 2 * o.clearance_m, 0.9, o, free_axis=None))
            # leaning along the axis: the jaws stay on the same diameter
            out.extend(_tilted(gid, base, 2 * r + 2 * o.clearance_m, 0.9, o))
            # across the caps, approached from the side (closing along the axis)
        pos = c - approach * (r - depth)
        out.append(_g(f"cyl_caps_{k}", "parallel", tcp_frame(approach, axis, pos), length + 2 * o.clearance_m, 0.7, o))
    for s in (1.0, -1.0):
        approach = s * axis
        depth = o.depth(length)
        for k in range(max(o.side_angles // 2, 1)):
            ang = np.pi * k / max(o.side_angles // 2, 1)
            closing = np.cos(ang) * u + np.sin(ang) * v
            pos = c - approach * (length / 2.0 - depth)
            out.append(
                _g(
                    f"cyl_top_{'+' if s > 0 else '-'}_{k}",
                    "parallel",
                    tcp_frame(approach, closing, pos),
                    2 * r + 2 * o.clearance_m,
                    1.0,
                    o,
                )
            )
        if 2 * r >= o.cup_diameter_m:
            out.append(
                _g(
                    f"cyl_cap_suction_{'+' if s > 0 else '-'}",
                    "suction",
                    tcp_frame(approach, u, c - approach * length / 2.0),
                    0.0,
                    1.0,
                    o,
                )
            )
    if length >= o.cup_diameter_m and r >= o.cup_diameter_m:
        for k in range(o.side_angles):
            ang = 2 * np.pi * k / o.side_angles
            approach = -(np.cos(ang) * u + np.sin(ang) * v)
            out.append(_g(f"cyl_side_suction_{k}", "suction", tcp_frame(approach, axis, c - approach * r), 0.0, 0.5, o))
    return out


def _fibonacci(n: int) -> FloatArray:
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    theta = np.pi * (1 + 5**0.5) * i
    return np.column_stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)])


def _sphere(t: Template, o: SynthesisOptions) -> list[GraspAnnotation]:
    v = np.asarray(t.mesh.vertices, dtype=np.float64)
    c = (v.max(axis=0) + v.min(axis=0)) / 2.0
    r = float(np.linalg.norm(v - c, axis=1).max())
    out = []
    for k, d in enumerate(_fibonacci(2 * o.side_angles)):
        approach = -d
        u, w = _perpendicular(approach)
        depth = o.depth(2 * r)
        for m, closing in enumerate((u, w)):
            out.append(
                _g(
                    f"sphere_{k}_{m}",
                    "parallel",
                    tcp_frame(approach, closing, c - approach * (r - depth)),
                    2 * r + 2 * o.clearance_m,
                    0.9,
                    o,
                )
            )
        if r >= o.cup_diameter_m:
            out.append(_g(f"sphere_suction_{k}", "suction", tcp_frame(approach, u, c - approach * r), 0.0, 0.6, o))
    return out


def _plate(t: Template, o: SynthesisOptions) -> list[GraspAnnotation]:
    frame, ext = _obb(t)
    rot, c = frame[:3, :3], frame[:3, 3]
    n_idx = int(np.argmin(ext))
    a_idx, b_idx = [m for m in range(3) if m != n_idx]
    normal = rot[:, n_idx]
    out = []
    offsets = [(0.0, 0.0)] + [(sa * ext[a_idx] / 4, sb * ext[b_idx] / 4) for sa in (-1, 1) for sb in (-1, 1)]
    for s in (1.0, -1.0):
        approach = -s * normal
        for k, (da, db) in enumerate(offsets):
            pos = c + s * normal * ext[n_idx] / 2.0 + da * rot[:, a_idx] + db * rot[:, b_idx]
            out.append(
                _g(
                    f"plate_suction_{'+' if s > 0 else '-'}_{k}",
                    "suction",
                    tcp_frame(approach, rot[:, a_idx], pos),
                    0.0,
                    1.0 if k == 0 else 0.8,
                    o,
                )
            )
    for e_idx in (a_idx, b_idx):
        depth = min(ext[e_idx] / 2.0, o.max_grip_depth_m)  # in-plane: the tips stay inside the plate outline
        for s in (1.0, -1.0):
            approach = s * rot[:, e_idx]
            pos = c - approach * (ext[e_idx] / 2.0 - depth)
            out.append(
                _g(
                    f"plate_edge_{e_idx}{'+' if s > 0 else '-'}",
                    "parallel",
                    tcp_frame(approach, normal, pos),
                    ext[n_idx] + 2 * o.clearance_m,
                    0.7,
                    o,
                )
            )
    # a plate lying on its face: pinch across its width or length from above / below (the tips reach down the
    # rim; the planner raises them off the surface underneath)
    # Like box pinches, these are also offered slid along the jaw width (long sides). Not tilted: on a part this
    # thin, a tilted pinch leaves the jaw tips too little rim (physics: the plate slips out or is missed).
    depth = o.depth(float(ext[n_idx]))
    for e_idx in (a_idx, b_idx):
        w_idx = b_idx if e_idx == a_idx else a_idx
        slides = [0.0] if ext[w_idx] < o.slide_min_m else [0.0, -ext[w_idx] / 4.0, ext[w_idx] / 4.0]
        for s in (1.0, -1.0):
            approach = -s * normal
            for n_slide, slide in enumerate(slides):
                pos = c + s * normal * (ext[n_idx] / 2.0 - depth) + rot[:, w_idx] * slide
                gid = f"plate_across_{e_idx}{'+' if s > 0 else '-'}" + (f"_s{n_slide}" if n_slide else "")
                quality = 0.6 - (0.1 if n_slide else 0.0)
                pose = tcp_frame(approach, rot[:, e_idx], pos)
                out.append(_g(gid, "parallel", pose, ext[e_idx] + 2 * o.clearance_m, quality, o))
    return out


def _antipodal(t: Template, o: SynthesisOptions) -> list[GraspAnnotation]:
    """Antipodal pairs: sample surface points, shoot a ray inwards along -normal, keep pairs whose contact normals
    both lie inside the friction cone (half angle atan(mu)) of the line joining them."""
    mesh = t.mesh
    rng = np.random.default_rng(o.seed)
    points, face_idx = _sample_surface(mesh, o.antipodal_samples, rng)
    normals = np.asarray(mesh.face_normals, dtype=np.float64)[face_idx]
    origins = points - normals * 1e-4
    locs, ray_idx, tri_idx = mesh.ray.intersects_location(origins, -normals, multiple_hits=False)
    cone = np.arctan(o.friction_coef)
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    out: list[GraspAnnotation] = []
    for loc, ri, ti in zip(locs, ray_idx, tri_idx, strict=False):
        p1, n1 = points[ri], normals[ri]
        n2 = np.asarray(mesh.face_normals[ti], dtype=np.float64)
        axis = loc - p1
        width = float(np.linalg.norm(axis))
        if width < 2e-3:
            continue
        axis /= width
        a1 = np.arccos(np.clip(np.dot(axis, -n1), -1, 1))
        a2 = np.arccos(np.clip(np.dot(axis, n2), -1, 1))
        if a1 > cone or a2 > cone:
            continue
        quality = float(1.0 - max(a1, a2) / max(cone, 1e-9) * 0.5)
        mid = (p1 + loc) / 2.0
        u, w = _perpendicular(axis)
        for k in range(4):
            ang = np.pi / 2 * k
            approach = np.cos(ang) * u + np.sin(ang) * w
            # back the TCP off so the jaw tips stop 2 mm short of the part's far side along the approach
            far = float(((verts - mid) @ approach).max())
            tcp = mid - approach * max(0.0, o.finger_tip_m + 0.002 - far)
            out.append(
                _g(
                    f"antipodal_{ri}_{k}",
                    "parallel",
                    tcp_frame(approach, axis, tcp),
                    width + 2 * o.clearance_m,
                    quality,
                    o,
                )
            )
    return out


def _sample_surface(mesh: object, n: int, rng: np.random.Generator) -> tuple[FloatArray, np.ndarray]:
    """Area-weighted surface samples with a local RNG (trimesh's sampler would use the global one)."""
    tris = np.asarray(mesh.triangles, dtype=np.float64)  # type: ignore[attr-defined]
    areas = np.asarray(mesh.area_faces, dtype=np.float64)  # type: ignore[attr-defined]
    face_idx = rng.choice(len(areas), size=n, p=areas / areas.sum())
    uv = rng.random((n, 2))
    flip = uv.sum(axis=1) > 1
    uv[flip] = 1 - uv[flip]
    t = tris[face_idx]
    pts = t[:, 0] + uv[:, :1] * (t[:, 1] - t[:, 0]) + uv[:, 1:] * (t[:, 2] - t[:, 0])
    return pts, face_idx


def _facet_suction(t: Template, o: SynthesisOptions) -> list[GraspAnnotation]:
    """Suction at the centre of every flat facet big enough for the cup (cup centre must lie on the facet)."""
    mesh = t.mesh
    out = []
    cup_area = np.pi * (o.cup_diameter_m / 2.0) ** 2
    facets = list(mesh.facets)
    normals = np.asarray(mesh.facets_normal, dtype=np.float64) if facets else np.zeros((0, 3))
    areas = np.asarray(mesh.facets_area, dtype=np.float64) if facets else np.zeros(0)
    for k, (faces, n, area) in enumerate(zip(facets, normals, areas, strict=True)):
        if area < 2 * cup_area:
            continue
        tris = np.asarray(mesh.triangles[faces], dtype=np.float64)
        tri_area = np.asarray(mesh.area_faces[faces], dtype=np.float64)
        centre = (tris.mean(axis=1) * tri_area[:, None]).sum(axis=0) / tri_area.sum()
        u, _ = _perpendicular(-n)
        out.append(
            _g(f"facet_suction_{k}", "suction", tcp_frame(-n, u, centre), 0.0, 0.5 + 0.5 * min(area / 0.01, 1.0), o)
        )
    return out
