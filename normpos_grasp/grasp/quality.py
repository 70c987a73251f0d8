"""Grasp quality from mechanics: will the part stay in the hand once it is lifted and carried?

Parallel jaws (TCP frame: z approach, x closing). The template surface is sampled once (area-weighted points with
their face normals, cached per template) and put in the TCP frame of the grasp. Each flat pad touches what lies in
its footprint (finger width across y, finger length along z) within `contact_band_m` of the innermost surface
point along the closing axis. From that patch:
- friction cone and pad area: the touched surface whose normals lie inside the pad's friction cone atan(mu) must
  cover at least `min_area_m2` on both pads;
- squeeze balance (antipodal): the line between the two patch centroids must lie within `flat_face_rad` of the
  closing axis (faces flat on the pads, or round surfaces), or each pad must touch a face within `flat_face_rad`
  of lying flat on it; otherwise (the edges of a bar rolled 25 degrees under flat pads) the squeeze couple turns
  the part until its faces lie flat, which the physics judge counts as slip beyond 0.2 rad (MuJoCo's soft
  contacts creep under that couple even inside the rigid friction cone);
- load: the part's weight times `load_factor` (lift and transfer accelerations) as a force along the pads and a
  torque about the squeeze line (the centre of mass off that line: the bar turning in the jaws), against what
  the pads hold at the grip force, mu F per pad for the force and mu F mean(rho) + mu_t F per pad for the torque
  (uniform pressure on the patch, rho the patch points' distance from the squeeze line; mu_t the pads' torsional
  friction length), combined on an elliptic limit surface: (f / f_max)^2 + (tau / tau_max)^2 <= 1.
Suction: the cup footprint must seal on the FITTED surface (`sim.physics_suction.check_seal` on the template in
its fitted pose: every ray under the cup hits, height spread within the lip's compliance, normals facing the cup),
the vacuum force must carry the weight times `load_factor`, and the payload torque about the cup's rim (weight
times the centre of mass's offset from the cup axis) must stay under the cup's peel limit F_vac r / 4 (a disc
pressed with a linear pressure profile opens on one side at that moment).

`GraspMechanics.margin` (1 - the limit-surface ratio, cut by the cone and area margins) is mapped to a predicted
success probability by the calibration table `CALIBRATION` (margin bin -> success observed in MuJoCo, measured by
`benchmarks/bench_grasp_quality.py --fit`); that benchmark prints predicted against observed success per bin.
Newtons, metres, kilograms, radians.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import lru_cache
from typing import Any

import numpy as np

from normpos_grasp.geometry.transforms import invert_pose
from normpos_grasp.records.tool import ToolModel
from normpos_grasp.typing import FloatArray

GRAVITY_M_S2 = 9.81

#: (lower edge of the mechanics-margin bin, predicted success) in increasing margin order; a margin <= 0 is a
#: predicted failure. The two upper bins: the share held in MuJoCo on the fit seeds (`benchmarks/bench_grasp_quality.py
#: --fit --seed 300`: 3 / 3 and 92 / 92); the two lower ones saw no grasp there and keep a monotone prior.
CALIBRATION: tuple[tuple[float, float], ...] = ((0.0, 0.5), (0.25, 0.8), (0.5, 1.0), (0.75, 1.0))

#: reasons a candidate gets from `judge` when the mechanics say it will not hold
MECHANICS_REASONS = ("friction_cone", "pad_contact", "slip_torque", "seal", "suction_load", "suction_torque")


@dataclass(frozen=True)
class QualityOptions:
    """Mechanics of the grip. friction: Coulomb friction of pads (and cup lip) on the part; flat_face_rad: the
    largest turn of the squeeze line off the closing axis, or of a touched face off lying flat on its pad, rad
    (under the physics judge's 0.2 rad slip tolerance); torsional_m: the pads' torsional friction length (torque
    mu_t F per pad), m; grip_force_n: squeeze force per finger, N (defaults: the physics judge's 2F-85 at 100 N,
    `sim.physics.GripperSpec`); contact_band_m: surface within this of the innermost point under a pad counts as
    touched (pad compliance and fit noise), m; min_area_m2: least touched area inside the pad's friction cone, per
    pad, m^2; samples: surface samples per template; load_factor: weight multiplier for the accelerations of lift
    and transfer; cup_diameter_m, vacuum_kpa, vacuum_efficiency: the suction cup (defaults: the physics judge's
    cup; `judge` takes the tool's own cup); seal_flatness_m / seal_normal_rad: the seal criteria
    (`sim.physics_suction.SealOptions`); seal_margin_m: the error of the fitted pose the seal must tolerate: the
    footprint checked is the cup widened by this on every side (a 30 mm cup on a 30 mm face seals only when the fit
    is exact, and a real part sits a millimetre or two from its fit), m.
    """

    friction: float = 0.9
    flat_face_rad: float = 0.15
    torsional_m: float = 0.004
    grip_force_n: float = 100.0
    contact_band_m: float = 0.0015
    min_area_m2: float = 5e-6
    samples: int = 6000
    load_factor: float = 2.0
    cup_diameter_m: float = 0.03
    vacuum_kpa: float = 60.0
    vacuum_efficiency: float = 0.8
    seal_flatness_m: float = 0.004
    seal_normal_rad: float = 0.45
    seal_margin_m: float = 0.002


@dataclass(frozen=True)
class GraspMechanics:
    """Verdict of one grasp. ok: the mechanics say it holds; reason: '' or one of MECHANICS_REASONS; margin in
    (-inf, 1]: 1 - load ratio, cut by the cone and area margins (<= 0 when not ok); success: predicted success
    probability (`predicted_success(margin)`); area_m2: smaller pad patch (parallel) or cup area (suction);
    cone_angle_rad: largest angle of the touched normals (or of the squeeze line) from the pad normal;
    load_ratio: the limit-surface ratio (force and torque over what the grip holds)."""

    ok: bool
    reason: str
    margin: float
    success: float
    area_m2: float
    cone_angle_rad: float
    load_ratio: float


def predicted_success(margin: float) -> float:
    """Predicted success of a grasp with mechanics margin `margin` (the `CALIBRATION` table; 0 below 0)."""
    if not np.isfinite(margin) or margin <= 0.0:
        return 0.0
    p = CALIBRATION[0][1]
    for lower, value in CALIBRATION:
        if margin >= lower:
            p = value
    return float(p)


@lru_cache(maxsize=64)
def _surface(mesh: Any, n: int) -> tuple[FloatArray, FloatArray, float]:
    """(points (n, 3), unit face normals (n, 3), area per sample m^2) of `mesh` in its own frame: area-weighted
    samples with a fixed seed (deterministic), cached per mesh object."""
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces)
    tri = verts[faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    areas = 0.5 * np.linalg.norm(cross, axis=1)
    total = float(areas.sum())
    normals = cross / np.maximum(2.0 * areas, 1e-18)[:, None]
    rng = np.random.default_rng(0)
    face = rng.choice(len(faces), size=n, p=areas / total)
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1.0
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    t = tri[face]
    pts = t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])
    return pts, normals[face], total / n


def pad_footprint(tool: ToolModel) -> tuple[float, float, float]:
    """(half width across y, lowest z, highest z) of the finger pads in the TCP frame, m, from the tool's moving
    shapes (the fingers)."""
    fingers = [s for s in tool.shapes if s.moves]
    if not fingers:
        tip = float(tool.finger_depth_m)
        return 0.0135, tip - 0.062, tip
    half_w = min(float(s.size[1]) / 2.0 for s in fingers)
    z = [float(np.asarray(s.tcp_from_shape)[2, 3]) for s in fingers]
    half_l = [float(s.size[2]) / 2.0 for s in fingers]
    return (
        half_w,
        max(zc - hl for zc, hl in zip(z, half_l, strict=True)),
        min(zc + hl for zc, hl in zip(z, half_l, strict=True)),
    )


def parallel_mechanics(
    mesh: Any,
    mass_kg: float,
    world_from_object: FloatArray,
    world_from_tcp: FloatArray,
    footprint: tuple[float, float, float],
    options: QualityOptions | None = None,
) -> GraspMechanics:
    """Mechanics of a parallel-jaw grasp at `world_from_tcp` (4, 4) on `mesh` (object frame) posed at
    `world_from_object` (4, 4); `footprint` from `pad_footprint`."""
    opts = options or QualityOptions()
    pts, nrm, da = _surface(mesh, int(opts.samples))
    tcp_from_object = invert_pose(np.asarray(world_from_tcp, dtype=np.float64)) @ world_from_object
    rot, trans = tcp_from_object[:3, :3], tcp_from_object[:3, 3]
    p = pts @ rot.T + trans
    n = nrm @ rot.T
    half_w, z_lo, z_hi = footprint
    inside = (np.abs(p[:, 1]) <= half_w) & (p[:, 2] >= z_lo) & (p[:, 2] <= z_hi)
    cone = float(np.arctan(opts.friction))
    flat = min(float(opts.flat_face_rad), cone)
    cos_cone = float(np.cos(cone))
    if inside.sum() < 2:
        return GraspMechanics(False, "pad_contact", -1.0, 0.0, 0.0, np.pi, np.inf)
    pin, nin = p[inside], n[inside]
    patches = []
    best_face = 0.0  # the larger, over both pads, of the angle between the flattest touched face and the pad
    for sign in (-1.0, 1.0):  # left pad at -x (pushes along +x), right pad at +x
        x = sign * pin[:, 0]
        touched = x >= x.max() - opts.contact_band_m
        facing = touched & (nin[:, 0] * sign >= cos_cone)  # outward normal inside the friction cone of the pad
        area = float(facing.sum()) * da
        if area < opts.min_area_m2:
            reason = "friction_cone" if not facing.any() else "pad_contact"
            touched_angle = float(np.arccos(np.clip((nin[touched, 0] * sign).max(initial=-1.0), -1.0, 1.0)))
            return GraspMechanics(False, reason, -1.0, 0.0, area, touched_angle, np.inf)
        best_face = max(best_face, float(np.arccos(np.clip((nin[facing, 0] * sign).max(), -1.0, 1.0))))
        patches.append((pin[facing], area))
    (left, a_left), (right, a_right) = patches
    c_left, c_right = left.mean(axis=0), right.mean(axis=0)
    line = c_right - c_left
    line_angle = float(np.arccos(np.clip(abs(line[0]) / max(np.linalg.norm(line), 1e-12), -1.0, 1.0)))
    # balanced (the squeeze line along the closing axis: faces flat on the pads, or round surfaces) or a face
    # that the squeeze lays flat on each pad with a small turn; otherwise the squeeze couple turns the part
    turn = min(line_angle, best_face)
    if turn > flat:
        return GraspMechanics(False, "friction_cone", -1.0, 0.0, min(a_left, a_right), turn, np.inf)
    worst_angle = turn
    mid = 0.5 * (c_left + c_right)
    # load in the TCP frame: weight through the centre of mass
    com_obj = np.asarray(getattr(mesh, "center_mass", np.asarray(mesh.bounds).mean(axis=0)), dtype=np.float64)
    com = rot @ com_obj + trans
    g_tcp = invert_pose(np.asarray(world_from_tcp, dtype=np.float64))[:3, :3] @ np.array([0.0, 0.0, -1.0])
    weight = float(mass_kg) * GRAVITY_M_S2 * opts.load_factor
    f = weight * g_tcp
    torque_x = float(np.cross(com - mid, f)[0])
    force_t = float(np.hypot(f[1], f[2]))  # along the pads (the squeeze carries none of it)
    force_n = float(abs(f[0]))  # along the closing axis: one pad pushes it, the other gives way
    grip = opts.grip_force_n
    f_max = 2.0 * opts.friction * grip
    rho = [np.linalg.norm(patch[:, 1:] - mid[1:], axis=1).mean() for patch, _ in patches]
    tau_max = sum(opts.friction * grip * float(r) + opts.torsional_m * grip for r in rho)
    ratio = float(np.sqrt((force_t / f_max) ** 2 + (torque_x / tau_max) ** 2)) + force_n / (2.0 * grip)
    area = min(a_left, a_right)
    margin = min(1.0 - ratio, 1.0 - worst_angle / cone, area / (area + opts.min_area_m2))
    if ratio >= 1.0:
        return GraspMechanics(False, "slip_torque", min(margin, 0.0), 0.0, area, worst_angle, ratio)
    return GraspMechanics(True, "", margin, predicted_success(margin), area, worst_angle, ratio)


def suction_mechanics(
    mesh: Any,
    mass_kg: float,
    world_from_object: FloatArray,
    world_from_tcp: FloatArray,
    options: QualityOptions | None = None,
) -> GraspMechanics:
    """Mechanics of a suction grasp at `world_from_tcp` (4, 4) on `mesh` posed at `world_from_object` (4, 4): the
    seal on the fitted surface (the cup widened by `seal_margin_m` on every side), then weight and payload torque
    against the vacuum."""
    import trimesh

    from normpos_grasp.sim.physics_suction import SealOptions, check_seal, vacuum_force_n

    opts = options or QualityOptions()
    w_obj = np.asarray(world_from_object, dtype=np.float64)
    w_tcp = np.asarray(world_from_tcp, dtype=np.float64)
    mesh_world = _posed_mesh(mesh, w_obj, trimesh)
    seal = check_seal(
        mesh_world,
        w_tcp,
        opts.cup_diameter_m + 2.0 * opts.seal_margin_m,
        SealOptions(flatness_m=opts.seal_flatness_m, max_normal_angle_rad=opts.seal_normal_rad),
    )
    r = opts.cup_diameter_m / 2.0
    area = float(np.pi * r * r)
    if not seal.sealed:
        return GraspMechanics(False, "seal", -1.0, 0.0, area * seal.hit_fraction, seal.max_normal_angle_rad, np.inf)
    f_vac = vacuum_force_n(opts.cup_diameter_m, opts.vacuum_kpa, opts.vacuum_efficiency)
    weight = float(mass_kg) * GRAVITY_M_S2 * opts.load_factor
    com_obj = np.asarray(getattr(mesh, "center_mass", np.asarray(mesh.bounds).mean(axis=0)), dtype=np.float64)
    com = w_obj[:3, :3] @ com_obj + w_obj[:3, 3]
    axis = w_tcp[:3, 2]
    down = np.array([0.0, 0.0, -1.0])
    # the weight pulls the part off the cup along the axis and shears it across the lip (friction holds that)
    pull = weight * max(float(axis @ down), 0.0)
    shear = weight * float(np.linalg.norm(np.cross(axis, down)))
    load = max(pull / f_vac, shear / (opts.friction * f_vac))
    # the weight's moment about the cup centre peels the lip off on one side at F_vac r / 4
    moment = float(np.linalg.norm(np.cross(com - w_tcp[:3, 3], weight * down)))
    torque = moment / (f_vac * r / 4.0)
    ratio = max(load, torque)
    margin = min(1.0 - ratio, 1.0 - seal.max_normal_angle_rad / opts.seal_normal_rad)
    if load >= 1.0:
        return GraspMechanics(False, "suction_load", min(margin, 0.0), 0.0, area, seal.max_normal_angle_rad, ratio)
    if torque >= 1.0:
        return GraspMechanics(False, "suction_torque", min(margin, 0.0), 0.0, area, seal.max_normal_angle_rad, ratio)
    return GraspMechanics(True, "", margin, predicted_success(margin), area, seal.max_normal_angle_rad, ratio)


def measured_seal(points: FloatArray, world_from_tcp: FloatArray, options: QualityOptions | None = None) -> bool:
    """Whether a suction cup at `world_from_tcp` (4, 4; approach along its z) seals on measured surface points
    (N, 3, world, m) of an object no template explains: within the cup's footprint widened by `seal_margin_m`, every
    one of 12 sectors of its outer ring holds at least two points (the lip lies on the measured object, not over its
    edge, the bin or a hole), and the points under the footprint lie within `seal_flatness_m` of each other along
    the approach (5th to 95th percentile: not a curved side or a step)."""
    opts = options or QualityOptions()
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    g = np.asarray(world_from_tcp, dtype=np.float64)
    local = (pts - g[:3, 3]) @ g[:3, :3]  # TCP frame: z along the approach
    radius = opts.cup_diameter_m / 2.0 + opts.seal_margin_m
    r = np.hypot(local[:, 0], local[:, 1])
    under = (r <= radius) & (np.abs(local[:, 2]) <= 0.03)
    if np.count_nonzero(under) < 24:
        return False
    ring = under & (r >= 0.6 * radius)
    sector = (np.floor((np.arctan2(local[ring, 1], local[ring, 0]) + np.pi) / (2.0 * np.pi) * 12).astype(int)) % 12
    if np.min(np.bincount(sector, minlength=12)) < 2:
        return False
    z = local[under, 2]
    return bool(np.percentile(z, 95) - np.percentile(z, 5) <= opts.seal_flatness_m)


def _posed_mesh(mesh: Any, world_from_object: FloatArray, trimesh: Any) -> Any:
    verts = np.asarray(mesh.vertices, dtype=np.float64) @ world_from_object[:3, :3].T + world_from_object[:3, 3]
    return trimesh.Trimesh(vertices=verts, faces=np.asarray(mesh.faces), process=False)


def judge(
    scheme: str,
    mesh: Any,
    mass_kg: float,
    world_from_object: FloatArray,
    world_from_tcp: FloatArray,
    tool: ToolModel,
    options: QualityOptions | None = None,
    measured_points: FloatArray | None = None,
) -> GraspMechanics:
    """Mechanics verdict of one candidate: `parallel_mechanics` or `suction_mechanics` by scheme (with the tool's
    own cup where it gives one). measured_points (N, 3), world, m: an object no template explains (its mesh a box
    around them): a cup must also seal on them (`measured_seal`)."""
    if scheme == "suction":
        opts = options or QualityOptions()
        if tool.cup_diameter_m > 0.0:
            opts = replace(opts, cup_diameter_m=float(tool.cup_diameter_m))
        mech = suction_mechanics(mesh, mass_kg, world_from_object, world_from_tcp, opts)
        if mech.ok and measured_points is not None and not measured_seal(measured_points, world_from_tcp, opts):
            return GraspMechanics(False, "seal", -1.0, 0.0, mech.area_m2, mech.cone_angle_rad, np.inf)
        return mech
    return parallel_mechanics(mesh, mass_kg, world_from_object, world_from_tcp, pad_footprint(tool), options)
