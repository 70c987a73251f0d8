"""`normpos-grasp teach MESH_OR_TEMPLATE... --out LIBRARY [--units mm|m] [--budget-min N] [--segmenter-budget-min M]`:
CAD to a ready part.

Checks and repairs each mesh, finds its symmetries and resting poses, synthesizes grasps and validates them in
MuJoCo, stores the fit preparation and writes LIBRARY/<name>/ (template.yaml, mesh.stl, .prepared/, report.html);
with --segmenter-budget-min M > 0 it then teaches the segmentation model the library's parts on synthetic bins
within M minutes and writes LIBRARY/segmenter/ (normpos_seg.onnx, MODEL_CARD.md), which every command given
--library LIBRARY uses; see normpos_grasp.teach, docs/onboarding.md and docs/segmentation.md. Bad CAD (unreadable or
empty file, open mesh, a size that contradicts --units) is one line and exit code 2, and LIBRARY is left as it was.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from normpos_grasp.cli.args import OVERWRITE_HELP, float_in
from normpos_grasp.perception.factory import LIBRARY_SEGMENTER_DIR


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "teach",
        help="turn CAD files into ready parts of a library (symmetry, resting poses, validated grasps, report)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("sources", nargs="+", metavar="MESH_OR_TEMPLATE", help="mesh files (STL/OBJ/PLY/...) or "
                   "template folders (template.yaml + mesh)")  # fmt: skip
    p.add_argument("--out", type=Path, required=True, help="library folder to add the parts to (created)")
    p.add_argument("--units", choices=("mm", "m"), default="mm", help="units of the mesh files (default mm)")
    p.add_argument("--budget-min", type=float_in(0.01, 120.0, "min"), default=4.0,
                   help="wall-time budget per part, minutes (the grasp validation stops when it is spent)")  # fmt: skip
    p.add_argument("--segmenter-budget-min", type=float_in(0.0, 120.0, "min"), default=0.0,
                   help="wall-time budget for teaching the segmentation model the library's parts, minutes (0, the "
                   "default: skip; the library then uses the bundled model class-agnostically)")  # fmt: skip
    p.add_argument("--segmenter-cell", default="ur5e_bin_parallel",
                   help="cell whose bins the segmenter is taught on (packaged name or YAML; default "
                   "ur5e_bin_parallel)")  # fmt: skip
    p.add_argument("--gripper", default="2f85", help="parallel gripper for the grasp validation (2f85, 2f140 or a "
                   "packaged gripper)")  # fmt: skip
    p.add_argument("--material", default="pom", choices=("pom", "abs", "aluminium", "steel"),
                   help="material of bare meshes (sets the mass; default pom)")  # fmt: skip
    p.add_argument("--seed", type=int, default=0, help="seed of every random draw")
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP + " (a part of the same name)")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from normpos_grasp.teach import TeachOptions, gripper_spec, teach

    gripper_spec(args.gripper)  # an unknown gripper is refused before anything is read
    if args.segmenter_budget_min > 0:
        from normpos_grasp.cell import resolve_cell

        resolve_cell(args.segmenter_cell)  # an unknown cell is refused before anything is taught
    options = TeachOptions(
        units=args.units, budget_s=args.budget_min * 60.0, gripper=args.gripper, material=args.material, seed=args.seed,
        segmenter_budget_s=args.segmenter_budget_min * 60.0, segmenter_cell=args.segmenter_cell,
    )  # fmt: skip

    def progress(message: str) -> None:
        if not args.quiet:
            print(f"  {message}", file=sys.stderr)

    parts = teach(args.sources, args.out, options, progress, overwrite=args.overwrite)
    for part in parts:
        t = part.template
        rates = sorted(part.success.values(), reverse=True)
        best = f", best {rates[0]:.0%}" if rates else ""
        print(
            f"taught '{t.name}' (obj_id {t.obj_id}): symmetry {part.symmetry.summary}; {len(part.resting)} resting "
            f"poses (top {part.resting[0].probability:.0%}); {len(t.grasps)} grasps, {len(part.success)} validated"
            f"{best}; {part.timings['total']:.1f} s -> {part.folder}"
        )
    card = Path(args.out) / LIBRARY_SEGMENTER_DIR / "MODEL_CARD.md"
    if args.segmenter_budget_min > 0 and card.is_file():
        print(f"segmenter taught the library's parts -> {card.parent} (card: {card})")
    return 0
