"""Template libraries on disk: a folder per template (`template.yaml` + mesh) or a BOP models folder.

template.yaml (lengths in the declared `units`, mm or m; angles in degrees):

    name: bracket_l            # unique id (defaults to the folder name)
    label: bracket             # class label segmenters report (defaults to name)
    mesh: mesh.stl             # STL/OBJ/PLY/GLB, relative to the folder
    units: mm                  # mm | m
    shape: bracket             # box|cylinder|sphere|plate|bracket|ring|irregular
    mass_kg: 0.12
    material: aluminium
    symmetry:
      continuous: [{axis: [0, 0, 1], point: [0, 0, 0]}]
      discrete: [{axis: [1, 0, 0], angle_deg: 180, point: [0, 0, 0]}]   # or {matrix: 4x4 rows}
      generators: [{axis: [0, 0, 1], angle_deg: 90}, {axis: [1, 0, 0], angle_deg: 90}]  # whole group
    control_points: {corner_a: [0, 0, 0], hole_1: [20, 10, 5]}
    grasps:
      - {id: top, scheme: parallel, position: [0, 0, 30], rotvec_deg: [180, 0, 0], opening: 40, priority: 1}
"""

from __future__ import annotations

import json
import logging
import struct
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from normpos_grasp.errors import InputError, MeshError, TemplateError
from normpos_grasp.geometry.transforms import make_pose, rotation_from_rotvec, rotation_to_rotvec
from normpos_grasp.io.yaml_safe import load_yaml_file
from normpos_grasp.records.template import SHAPE_CLASSES, GraspAnnotation, Symmetry, Template
from normpos_grasp.templates.mesh_check import MeshReport, check_mesh
from normpos_grasp.typing import FloatArray
from normpos_grasp.validation import short_repr

logger = logging.getLogger(__name__)

UNITS = {"mm": 1e-3, "m": 1.0}
TEMPLATE_FILE = "template.yaml"
MESH_SUFFIXES = (".stl", ".obj", ".ply", ".glb", ".gltf", ".off")


@dataclass(frozen=True, eq=False)
class TemplateLibrary:
    """An ordered set of templates with lookups by name, label and BOP obj_id.

    templates: the templates. reports: mesh check report per template name. root: where it was loaded from.
    """

    templates: tuple[Template, ...]
    reports: dict[str, MeshReport] = field(default_factory=dict)
    root: str = ""

    def __post_init__(self) -> None:
        names = [t.name for t in self.templates]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise TemplateError(f"template names must be unique; duplicated: {dup}")

    def __len__(self) -> int:
        return len(self.templates)

    def __iter__(self) -> Iterator[Template]:
        return iter(self.templates)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(t.name for t in self.templates)

    @property
    def labels(self) -> tuple[str, ...]:
        return tuple(sorted({t.label for t in self.templates}))

    def get(self, name: str) -> Template:
        """The template called `name`; TemplateError listing the known names otherwise."""
        for t in self.templates:
            if t.name == name:
                return t
        raise TemplateError(f"no template named '{name}' in the library; known: {list(self.names)}")

    def by_label(self, label: str) -> tuple[Template, ...]:
        """Templates whose label (or name) equals `label` (may be empty)."""
        return tuple(t for t in self.templates if label in (t.label, t.name))

    def by_obj_id(self, obj_id: int) -> Template:
        """The template loaded from BOP object `obj_id`."""
        for t in self.templates:
            if t.obj_id == int(obj_id):
                return t
        raise TemplateError(f"no template with BOP obj_id {obj_id}; the library holds {self.describe()}")

    def label_of_obj_id(self, obj_id: int) -> str | None:
        """The label of the template with BOP `obj_id`, or None when the library has no such object."""
        for t in self.templates:
            if t.obj_id == int(obj_id):
                return t.label
        return None

    def describe(self) -> str:
        """One line naming every template with its obj_id ('cube (1), box (2), ...')."""
        return ", ".join(f"{t.name} ({t.obj_id})" for t in self.templates)

    def subset(self, names: Sequence[str]) -> TemplateLibrary:
        """The templates called `names` (order kept, repeats dropped); TemplateError listing what exists otherwise."""
        wanted = list(dict.fromkeys(str(n) for n in names))
        missing = [n for n in wanted if n not in self.names]
        if missing:
            raise TemplateError(f"unknown part names {missing}; the library holds {self.describe()}")
        by_name = {t.name: t for t in self.templates}
        reports = {n: self.reports[n] for n in wanted if n in self.reports}
        return TemplateLibrary(tuple(by_name[n] for n in wanted), reports, self.root)


# -- one library for every command -----------------------------------------------------------------

#: the name that stands for the built-in parts (sim.parts.default_part_library) in a list of libraries
BUILTIN = "builtin"


def builtin_library() -> TemplateLibrary:
    """The eight built-in procedural parts (obj_id 1..8), as a TemplateLibrary."""
    from normpos_grasp.sim.parts import default_part_library

    return TemplateLibrary(tuple(default_part_library()), {}, BUILTIN)


def resolve_library(paths: Sequence[str | Path] | None = None, *, repair: bool = True) -> TemplateLibrary:
    """The one part library of a command: the union of `paths`, in order (the built-in parts when empty).

    Each entry is a folder of template folders, one template folder, a BOP models folder, or `BUILTIN`
    ('builtin', the eight procedural parts). Names must be unique across the entries, and BOP obj_ids too;
    templates that declare no obj_id get the smallest ids above every declared one, in order, so the same list of
    libraries always gives the same ids (`teach` writes an explicit id into every template it makes).

    Raises:
        TemplateError: an entry holds no template, two entries share a name or an obj_id (both sources named).
    """
    entries = [str(p) for p in (paths or ())] or [BUILTIN]
    parts: list[Template] = []
    reports: dict[str, MeshReport] = {}
    origin: dict[str, str] = {}
    for entry in dict.fromkeys(entries):
        lib = builtin_library() if entry == BUILTIN else load_library(entry, repair=repair)
        for t in lib:
            if t.name in origin:
                raise TemplateError(
                    f"part name '{t.name}' is in both {origin[t.name]} and {entry}; rename one (template.yaml 'name:')"
                )
            origin[t.name] = entry
            parts.append(t)
        reports.update(lib.reports)
    ids: dict[int, str] = {}
    for t in parts:
        if t.obj_id >= 0:
            if t.obj_id in ids:
                raise TemplateError(
                    f"obj_id {t.obj_id} is used by '{ids[t.obj_id]}' ({origin[ids[t.obj_id]]}) and '{t.name}' "
                    f"({origin[t.name]}); give one of them another 'obj_id:' in its template.yaml"
                )
            ids[t.obj_id] = t.name
    next_id = max(ids, default=0) + 1
    out = []
    for t in parts:
        if t.obj_id < 0:
            t = replace(t, obj_id=next_id)
            logger.info("template '%s' declares no obj_id: it gets %d in this library", t.name, next_id)
            next_id += 1
        out.append(t)
    root = entries[0] if len(entries) == 1 else ";".join(entries)
    return TemplateLibrary(tuple(out), reports, root)


# -- loading ---------------------------------------------------------------------------------------


def load_library(path: str | Path, *, repair: bool = True) -> TemplateLibrary:
    """Load a template library: a folder of template folders, one template folder, or a BOP models folder.

    Raises:
        TemplateError: the path does not exist or holds no template (an empty library is an error).
    """
    root = Path(path)
    if not root.exists():
        raise TemplateError(f"template library '{root}' does not exist")
    if root.is_file() and root.name == "models_info.json":
        root = root.parent
    if (root / "models_info.json").is_file():
        templates = load_bop_models(root, repair=repair)
    elif (root / TEMPLATE_FILE).is_file():
        templates = [load_template(root, repair=repair)]
    else:
        folders = sorted(p for p in root.iterdir() if (p / TEMPLATE_FILE).is_file())
        templates = [load_template(p, repair=repair) for p in folders]
    if not templates:
        raise TemplateError(
            f"no templates in '{root}': expected sub-folders with {TEMPLATE_FILE} or a BOP models_info.json"
        )
    reports = {t.name: t.report for t in templates if t.report is not None}
    return TemplateLibrary(tuple(templates), reports, str(root))


def load_template(folder: str | Path, *, repair: bool = True) -> Template:
    """Load one template folder (`template.yaml` + mesh); lengths converted to metres."""
    folder = Path(folder)
    spec_path = folder / TEMPLATE_FILE
    if not spec_path.is_file():
        raise TemplateError(f"'{folder}' has no {TEMPLATE_FILE}")
    try:
        spec = load_yaml_file(spec_path)
    except yaml.YAMLError as exc:
        raise TemplateError(str(exc)) from exc  # one line: file:line:col: problem
    if not isinstance(spec, dict):
        raise TemplateError(f"{spec_path}: expected a mapping at the top level, got {type(spec).__name__}")
    where = str(spec_path)
    _check_keys(spec, TEMPLATE_KEYS, where, "")
    name = _text(spec.get("name", folder.name), f"{where}: name")
    units = str(spec.get("units", "m"))
    if units not in UNITS:
        raise TemplateError(f"{where}: units must be one of {sorted(UNITS)}, got '{units}'")
    scale = UNITS[units]
    mesh_name = spec.get("mesh")
    if mesh_name is None:
        found = sorted(p for p in folder.iterdir() if p.suffix.lower() in MESH_SUFFIXES)
        if len(found) != 1:
            raise TemplateError(f"{where}: give 'mesh:' (found {len(found)} mesh files in the folder)")
        mesh_path = found[0]
    else:
        mesh_path = folder / str(mesh_name)
    raw = _load_mesh(mesh_path, where)
    _check_units(raw.extents, units, where)
    raw.apply_scale(scale)
    mesh, report = check_mesh(raw, name, repair=repair)
    shape = str(spec.get("shape", "irregular"))
    if shape not in SHAPE_CLASSES:
        raise TemplateError(f"{where}: shape must be one of {SHAPE_CLASSES}, got '{shape}'")
    control_spec = spec.get("control_points") or {}
    if not isinstance(control_spec, dict):
        raise TemplateError(
            f"{where}: control_points: expected a mapping name: [x, y, z], got {short_repr(control_spec)}"
        )
    control = {str(k): _vec(v, f"{where}: control_points.{k}") * scale for k, v in control_spec.items()}
    symmetry_spec = spec.get("symmetry") or {}
    if not isinstance(symmetry_spec, dict):
        raise TemplateError(f"{where}: symmetry: expected a mapping, got {short_repr(symmetry_spec)}")
    _check_keys(symmetry_spec, ("continuous", "discrete", "generators"), where, "symmetry.")
    symmetry = _parse_symmetry(symmetry_spec, scale, where)
    grasp_specs = spec.get("grasps") or []
    if not isinstance(grasp_specs, list):
        raise TemplateError(f"{where}: grasps: expected a list, got {short_repr(grasp_specs)}")
    grasps = tuple(_parse_grasp(g, scale, f"{where}: grasps[{i}]") for i, g in enumerate(grasp_specs))
    ids = [g.id for g in grasps]
    if len(set(ids)) != len(ids):
        raise TemplateError(f"{where}: grasps: ids must be unique, got {ids}")
    mass = _number(spec.get("mass_kg", 0.1), f"{where}: mass_kg")
    if not mass > 0:
        raise TemplateError(f"{where}: mass_kg must be positive, got {mass}")
    obj_id = spec.get("obj_id", -1)
    if isinstance(obj_id, bool) or not isinstance(obj_id, int) or not (obj_id >= 1 or obj_id == -1):
        raise TemplateError(
            f"{where}: obj_id: expected a whole number >= 1 (a BOP object id), got {short_repr(obj_id)}"
        )
    _check_placement(mesh, control, grasps, where)
    _check_symmetry_on_mesh(mesh, symmetry, where)
    return Template(
        name=name,
        label=_text(spec.get("label", name), f"{where}: label"),
        mesh=mesh,
        control_points=control,
        symmetry=symmetry,
        grasps=grasps,
        shape=shape,
        mass_kg=mass,
        material=str(spec.get("material", "") or ""),
        source=str(folder),
        obj_id=obj_id,
        units=units,
        report=report,
    )


# the keys a template.yaml may hold (teach adds its record under `teach`) and a grasp entry's keys
TEMPLATE_KEYS = (
    "name", "label", "mesh", "units", "shape", "mass_kg", "material", "obj_id", "symmetry", "control_points",
    "grasps", "teach",
)  # fmt: skip
GRASP_KEYS = (
    "id", "scheme", "position", "rotvec_deg", "matrix", "opening", "priority", "approach", "retreat", "free_axis",
    "tilt_cone_deg", "success_rate", "trials",
)  # fmt: skip


def _check_keys(spec: dict[str, Any], allowed: Sequence[str], where: str, prefix: str) -> None:
    """TemplateError for a key the format does not have (a typo would otherwise be ignored silently)."""
    import difflib

    for key in spec:
        if str(key) not in allowed:
            close = difflib.get_close_matches(str(key), allowed, n=1)
            hint = f"; did you mean '{close[0]}'?" if close else ""
            raise TemplateError(f"{where}: {prefix}{key}: unknown key{hint} allowed here: {', '.join(allowed)}")


def _text(value: Any, where: str) -> str:
    if not isinstance(value, str | int) or isinstance(value, bool) or not str(value).strip():
        raise TemplateError(f"{where}: expected non-empty text, got {short_repr(value)}")
    return str(value)


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not np.isfinite(float(value)):
        raise TemplateError(f"{where}: expected a finite number, got {short_repr(value)}")
    return float(value)


def _check_placement(
    mesh: Any, control: dict[str, FloatArray], grasps: tuple[GraspAnnotation, ...], where: str
) -> None:
    """Control points and grasp TCPs must lie at the part: inside its bounding box grown by half its diagonal
    (at least 20 mm for grasps: a TCP sits between the fingertips or on the cup's lip). A point far off is a
    coordinate in the wrong units or frame, never a usable fit point or grasp."""
    lo, hi = np.asarray(mesh.bounds, dtype=np.float64)
    diag = float(np.linalg.norm(hi - lo))

    def outside(p: FloatArray, margin: float) -> float:
        return float(np.linalg.norm(np.maximum(lo - margin - p, 0.0) + np.maximum(p - hi - margin, 0.0)))

    for name, p in control.items():
        if outside(p, 0.5 * diag) > 0.0:
            raise TemplateError(
                f"{where}: control_points.{name}: {np.round(p * 1e3, 1).tolist()} mm lies "
                f"{(outside(p, 0.0)) * 1e3:.0f} mm outside the part's bounding box; check its units and frame"
            )
    for g in grasps:
        p = g.object_from_tcp[:3, 3]
        if outside(p, max(0.5 * diag, 0.02)) > 0.0:
            raise TemplateError(
                f"{where}: grasp {g.id!r}: its TCP {np.round(p * 1e3, 1).tolist()} mm lies "
                f"{outside(p, 0.0) * 1e3:.0f} mm outside the part's bounding box; check its units and frame"
            )


def _check_symmetry_on_mesh(mesh: Any, symmetry: Symmetry, where: str, n: int = 600) -> None:
    """Every declared symmetry must map the surface onto itself: `n` surface samples, moved by each discrete
    transform (and by three unrelated turns about each continuous axis), must land within 2 % of the part's
    diagonal (at least 1 mm) of the surface for 90 % of them. Loose on purpose: CAD details the declaration
    ignores (a logo, a chamfer, a thread) pass; a wrong axis or angle (a 90 degree turn of a 2:1 box) does not.
    A declared symmetry that is not one would make the fit treat different poses as the same."""
    if not symmetry.continuous and not symmetry.discrete:
        return
    import trimesh
    from scipy.spatial import cKDTree

    probe = np.asarray(trimesh.sample.sample_surface(mesh, n, seed=0)[0], dtype=np.float64)
    dense = np.asarray(trimesh.sample.sample_surface(mesh, 20000, seed=1)[0], dtype=np.float64)
    tree = cKDTree(dense)
    spacing = float(np.sqrt(float(mesh.area) / len(dense)))
    lo, hi = np.asarray(mesh.bounds, dtype=np.float64)
    tol = max(0.02 * float(np.linalg.norm(hi - lo)), 1e-3) + 2.0 * spacing
    moves: list[tuple[str, FloatArray]] = [
        (
            f"symmetry transform {i + 1} of {len(symmetry.discrete)} ({_rotation_text(t)})",
            np.asarray(t, dtype=np.float64),
        )
        for i, t in enumerate(symmetry.discrete)
    ]
    for i, (axis, point) in enumerate(symmetry.continuous):
        for angle in (23.0, 71.0, 137.0):
            rot = rotation_from_rotvec(np.asarray(axis) * np.deg2rad(angle))
            moves.append(
                (f"symmetry.continuous[{i}] (a {angle:g} degree turn)", make_pose(rot, point - rot @ np.asarray(point)))
            )
    for what, t in moves:
        moved = probe @ t[:3, :3].T + t[:3, 3]
        dist = tree.query(moved)[0]
        off = float(np.mean(dist > tol))
        if off > 0.10:
            raise TemplateError(
                f"{where}: {what} does not map the mesh onto itself ({100 * off:.0f} % of its surface lands more "
                f"than {tol * 1e3:.1f} mm from it); fix or remove it (`teach` finds the symmetries from the mesh)"
            )


def _rotation_text(t: FloatArray) -> str:
    rv = rotation_to_rotvec(np.asarray(t, dtype=np.float64)[:3, :3])
    angle = float(np.linalg.norm(rv))
    axis = rv / angle if angle > 1e-9 else np.array([0.0, 0.0, 1.0])
    return f"a turn about axis {np.round(axis, 3).tolist()} by {np.rad2deg(angle):.0f} degrees"


def load_bop_models(folder: str | Path, *, repair: bool = True) -> list[Template]:
    """Templates from a BOP models folder (`models_info.json` + `obj_XXXXXX.ply`, millimetres)."""
    folder = Path(folder)
    try:
        from normpos_grasp.io.bop import read_models  # another stage's reader, when present

        models = read_models(folder)
        items = [
            (
                int(m.obj_id),
                Path(m.mesh_path),
                [np.asarray(t, dtype=np.float64) for t in np.asarray(m.symmetries_discrete).reshape(-1, 4, 4)],
                [
                    (np.asarray(a, dtype=np.float64), np.asarray(o, dtype=np.float64))
                    for a, o in m.symmetries_continuous
                ],
            )
            for m in models.values()
        ]
    except ImportError:
        items = _read_bop_info(folder)
    out = []
    for obj_id, mesh_path, disc, cont in items:
        name = f"obj_{obj_id:06d}"
        raw = _load_mesh(mesh_path, str(folder / "models_info.json"))
        _check_units(raw.extents, "mm", str(mesh_path))
        raw.apply_scale(1e-3)
        mesh, report = check_mesh(raw, name, repair=repair)
        sym = Symmetry(
            continuous=tuple((a / np.linalg.norm(a), o) for a, o in cont),
            discrete=tuple(t for t in disc if not np.allclose(t, np.eye(4), atol=1e-6)),
        )
        out.append(
            Template(
                name=name,
                label=name,
                mesh=mesh,
                symmetry=sym,
                shape="irregular",
                source=str(mesh_path),
                obj_id=obj_id,
                units="mm",
                report=report,
            )
        )
    return out


def _read_bop_info(folder: Path) -> list[tuple[int, Path, list[FloatArray], list[tuple[FloatArray, FloatArray]]]]:
    info_path = folder / "models_info.json"
    try:
        info = json.loads(info_path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise TemplateError(f"{info_path}: cannot read BOP models info: {exc}") from exc
    items = []
    for key, entry in sorted(info.items(), key=lambda kv: int(kv[0])):
        obj_id = int(key)
        disc = []
        for flat in entry.get("symmetries_discrete", []):
            t = np.asarray(flat, dtype=np.float64).reshape(4, 4)
            t[:3, 3] *= 1e-3
            disc.append(t)
        cont = [
            (np.asarray(c["axis"], dtype=np.float64), np.asarray(c["offset"], dtype=np.float64) * 1e-3)
            for c in entry.get("symmetries_continuous", [])
        ]
        items.append((obj_id, folder / f"obj_{obj_id:06d}.ply", disc, cont))
    return items


def _load_mesh(path: Path, where: str) -> Any:
    import trimesh

    if not path.is_file():
        raise TemplateError(f"{where}: mesh file '{path}' not found")
    try:
        loaded = trimesh.load(str(path), force="mesh", process=False)
    except (ValueError, OSError, KeyError, IndexError, TypeError, AttributeError, EOFError, struct.error) as exc:
        # trimesh's readers raise these on truncated or malformed files
        raise MeshError(f"{where}: cannot read mesh '{path}': {exc}") from exc
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise MeshError(f"{where}: '{path}' holds no triangle mesh")
    if not np.all(np.isfinite(loaded.vertices)):
        raise MeshError(f"{where}: mesh '{path}' has NaN or infinite vertices; re-export it from CAD")
    loaded.process()  # what process=True would do (merge duplicate vertices), once the values are known finite
    return loaded


def _check_units(extents: Any, units: str, where: str) -> None:
    size = float(np.max(extents))
    if units == "mm" and size < 2.0:
        logger.warning(
            "%s: mesh is %.4g units across but units are mm (a %.4g mm part?): is it in metres?", where, size, size
        )
    if units == "m" and size > 2.0:
        logger.warning(
            "%s: mesh is %.4g units across but units are m (%.4g m): is it in millimetres?", where, size, size
        )


def _vec(value: Any, where: str, n: int = 3) -> FloatArray:
    try:
        arr = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise TemplateError(f"{where}: expected {n} numbers, got {value!r}") from exc
    if arr.shape != (n,) or not np.all(np.isfinite(arr)):
        raise TemplateError(f"{where}: expected {n} finite numbers, got {value!r}")
    return arr


def _parse_symmetry(spec: dict[str, Any], scale: float, where: str) -> Symmetry:
    cont = []
    for key in ("continuous", "discrete", "generators"):
        entries = spec.get(key) or []
        if not isinstance(entries, list) or not all(isinstance(e, dict) for e in entries):
            raise TemplateError(f"{where}: symmetry.{key}: expected a list of mappings, got {short_repr(entries)}")
    for i, c in enumerate(spec.get("continuous") or []):
        axis = _vec(c.get("axis"), f"{where}: symmetry.continuous[{i}].axis")
        if np.linalg.norm(axis) < 1e-9:
            raise TemplateError(f"{where}: symmetry.continuous[{i}].axis must be non-zero")
        point = _vec(c.get("point", [0, 0, 0]), f"{where}: symmetry.continuous[{i}].point") * scale
        cont.append((axis / np.linalg.norm(axis), point))
    disc = []
    gens = [
        _parse_rotation(d, scale, f"{where}: symmetry.generators[{i}]")
        for i, d in enumerate(spec.get("generators") or [])
    ]
    if gens:
        disc.extend(group_closure(gens, where))
    for i, d in enumerate(spec.get("discrete") or []):
        disc.append(_parse_rotation(d, scale, f"{where}: symmetry.discrete[{i}]"))
    return Symmetry(continuous=tuple(cont), discrete=tuple(_unique_transforms(disc)))


def _parse_rotation(d: dict[str, Any], scale: float, where: str) -> FloatArray:
    """A symmetry transform from {matrix: 4x4} or {axis, angle_deg, point} (lengths in file units)."""
    if not isinstance(d, dict):
        raise TemplateError(f"{where}: expected a mapping with 'matrix' or 'axis'/'angle_deg'")
    if "matrix" in d:
        try:
            t = np.asarray(d["matrix"], dtype=np.float64)
        except (TypeError, ValueError):
            raise TemplateError(f"{where}: matrix must be 4x4 numbers, got {short_repr(d['matrix'])}") from None
        if t.shape != (4, 4) or not np.all(np.isfinite(t)):
            raise TemplateError(f"{where}: matrix must be 4x4 finite numbers")
        t = t.copy()
        t[:3, 3] *= scale
    else:
        axis = _vec(d.get("axis"), f"{where}.axis")
        if np.linalg.norm(axis) < 1e-9:
            raise TemplateError(f"{where}.axis must be non-zero")
        angle = np.deg2rad(_number(d.get("angle_deg", 180.0), f"{where}.angle_deg"))
        point = _vec(d.get("point", [0, 0, 0]), f"{where}.point") * scale
        rot = rotation_from_rotvec(axis / np.linalg.norm(axis) * angle)
        t = make_pose(rot, point - rot @ point)
    rot = t[:3, :3]
    if not np.allclose(rot @ rot.T, np.eye(3), atol=1e-5) or np.linalg.det(rot) < 0:
        raise TemplateError(f"{where}: not a proper rotation")
    return t


def _unique_transforms(ts: list[FloatArray]) -> list[FloatArray]:
    out: list[FloatArray] = []
    for t in ts:
        if np.allclose(t, np.eye(4), atol=1e-6) or any(np.allclose(t, u, atol=1e-6) for u in out):
            continue
        out.append(t)
    return out


def group_closure(gens: list[FloatArray], where: str, limit: int = 120) -> list[FloatArray]:
    """All products of the generators (a finite symmetry group), identity excluded."""
    group = [np.eye(4)]
    frontier = [np.eye(4)]
    while frontier:
        nxt = []
        for a in frontier:
            for g in gens:
                p = g @ a
                if not any(np.allclose(p, q, atol=1e-6) for q in group):
                    group.append(p)
                    nxt.append(p)
                    if len(group) > limit:
                        raise TemplateError(f"{where}: symmetry generators do not form a finite group of <= {limit}")
        frontier = nxt
    return group[1:]


def _parse_grasp(g: dict[str, Any], scale: float, where: str) -> GraspAnnotation:
    if not isinstance(g, dict) or "id" not in g:
        raise TemplateError(f"{where}: a grasp needs at least 'id' and 'scheme'")
    _check_keys(g, GRASP_KEYS, where, "")
    scheme = str(g.get("scheme", "parallel"))
    if scheme not in ("parallel", "suction"):
        raise TemplateError(f"{where}: scheme must be 'parallel' or 'suction', got '{scheme}'")
    lengths = {}
    for key, default in (("opening", 0.0), ("approach", 0.08 / scale), ("retreat", 0.1 / scale)):
        value = _number(g.get(key, default), f"{where}.{key}")
        if value < 0:
            raise TemplateError(f"{where}.{key}: expected a length >= 0, got {value:g}")
        lengths[key] = value * scale
    priority = _number(g.get("priority", 0.0), f"{where}.priority")
    tilt_deg = _number(g.get("tilt_cone_deg", 0.0), f"{where}.tilt_cone_deg")
    if not 0.0 <= tilt_deg <= 90.0:
        raise TemplateError(f"{where}.tilt_cone_deg: expected 0-90 degrees, got {tilt_deg:g}")
    if "matrix" in g:
        try:
            pose = np.asarray(g["matrix"], dtype=np.float64).reshape(4, 4).copy()
        except (TypeError, ValueError):
            raise TemplateError(f"{where}.matrix: expected 4x4 numbers, got {short_repr(g['matrix'])}") from None
        rot = pose[:3, :3]
        if (
            not np.all(np.isfinite(pose))
            or not np.allclose(rot @ rot.T, np.eye(3), atol=1e-5)
            or np.linalg.det(rot) < 0
            or not np.allclose(pose[3], [0, 0, 0, 1])
        ):
            raise TemplateError(f"{where}.matrix: not a rigid transform (a proper rotation and a translation)")
        pose[:3, 3] *= scale
    else:
        pos = _vec(g.get("position", [0, 0, 0]), f"{where}.position") * scale
        rot = rotation_from_rotvec(np.deg2rad(_vec(g.get("rotvec_deg", [0, 0, 0]), f"{where}.rotvec_deg")))
        pose = make_pose(rot, pos)
    free = g.get("free_axis")
    free_axis = None if free is None else _vec(free, f"{where}.free_axis")
    if free_axis is not None and float(np.linalg.norm(free_axis)) < 1e-9:
        raise TemplateError(f"{where}.free_axis must be non-zero")
    return GraspAnnotation(
        id=_text(g["id"], f"{where}.id"),
        scheme=scheme,
        object_from_tcp=pose,
        opening_m=lengths["opening"],
        priority=priority,
        approach_m=lengths["approach"],
        retreat_m=lengths["retreat"],
        free_axis=free_axis,
        tilt_cone_rad=float(np.deg2rad(tilt_deg)),
    )


# -- saving ----------------------------------------------------------------------------------------


def save_template(template: Template, folder: str | Path, *, units: str = "mm", mesh_format: str = "stl") -> Path:
    """Write `template` as a folder (`template.yaml` + `mesh.<format>`) that `load_template` reads back.

    Returns the path of the written template.yaml.
    """
    if units not in UNITS:
        raise InputError(f"units must be one of {sorted(UNITS)}, got '{units}'")
    if mesh_format not in ("stl", "ply", "obj"):
        raise InputError(f"mesh_format must be stl, ply or obj, got '{mesh_format}'")
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    inv = 1.0 / UNITS[units]
    mesh = template.mesh.copy()
    mesh.apply_scale(inv)
    mesh_file = f"mesh.{mesh_format}"
    mesh.export(str(out / mesh_file))

    def r(v: Any) -> list[float]:
        return [float(round(x, 9)) for x in np.asarray(v, dtype=np.float64).reshape(-1)]

    spec: dict[str, Any] = {
        "name": template.name,
        "label": template.label,
        "mesh": mesh_file,
        "units": units,
        "shape": template.shape,
        "mass_kg": float(template.mass_kg),
        "material": template.material,
    }
    if template.obj_id >= 0:
        spec["obj_id"] = int(template.obj_id)
    sym: dict[str, Any] = {}
    if template.symmetry.continuous:
        sym["continuous"] = [{"axis": r(a), "point": r(np.asarray(p) * inv)} for a, p in template.symmetry.continuous]
    if template.symmetry.discrete:
        mats = []
        for t in template.symmetry.discrete:
            m = np.asarray(t, dtype=np.float64).copy()
            m[:3, 3] *= inv
            mats.append({"matrix": [r(row) for row in m]})
        sym["discrete"] = mats
    if sym:
        spec["symmetry"] = sym
    if template.control_points:
        spec["control_points"] = {k: r(np.asarray(v) * inv) for k, v in template.control_points.items()}
    if template.grasps:
        spec["grasps"] = [
            {
                "id": g.id,
                "scheme": g.scheme,
                "position": r(g.object_from_tcp[:3, 3] * inv),
                "rotvec_deg": r(np.rad2deg(rotation_to_rotvec(g.object_from_tcp[:3, :3]))),
                "opening": float(g.opening_m * inv),
                "priority": float(g.priority),
                "approach": float(g.approach_m * inv),
                "retreat": float(g.retreat_m * inv),
                "tilt_cone_deg": float(np.rad2deg(g.tilt_cone_rad)),
                **({} if g.free_axis is None else {"free_axis": r(g.free_axis)}),
            }
            for g in template.grasps
        ]
    path = out / TEMPLATE_FILE
    path.write_text(yaml.safe_dump(spec, sort_keys=False))
    return path


def save_library(library: TemplateLibrary | list[Template], folder: str | Path, *, units: str = "mm") -> Path:
    """Write every template into `folder/<name>/`; returns `folder`."""
    out = Path(folder)
    for t in library:
        save_template(t, out / t.name, units=units)
    return out
