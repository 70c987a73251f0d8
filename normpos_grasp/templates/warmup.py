"""Build the fit's compiled kernels ahead of use (`make install` runs it once after installing).

The kernels (`templates.kernels`) are compiled by numba on first use and cached on disk; a fresh install would
otherwise pay ~25-35 s of compilation inside its first fit (the demo's first pick). `warm_up` fits a small ray-cast
box through every code path the pipeline uses (with the depth image, without it, and with an unknown label), so
every kernel signature is compiled and written to the cache. `prepare_builtin` then prepares the built-in part
library and the example templates and stores their preparations (`prepared.prepare`), so a fresh process's first
fit of them loads it instead of paying ~1 s per template.

    python -m normpos_grasp.templates.warmup
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from normpos_grasp.camera.model import Camera
from normpos_grasp.geometry.transforms import make_pose, random_rotation
from normpos_grasp.records.template import Symmetry, Template, TemplateFit
from normpos_grasp.templates.fit import FitContext, FitOptions, fit_best, fit_many
from normpos_grasp.templates.prepared import prepare
from normpos_grasp.templates.scoring import evaluate
from normpos_grasp.templates.synthetic import render_views

logger = logging.getLogger(__name__)


def warm_up() -> tuple[float, list[TemplateFit]]:
    """Fit a ray-cast 60 x 40 x 20 mm box three ways; returns (seconds taken, the fits: labelled with the depth
    image, labelled without it, unlabelled with two templates to choose from)."""
    import trimesh

    t0 = time.perf_counter()
    flips = Symmetry(discrete=tuple(make_pose(np.diag(d)) for d in ((1.0, -1, -1), (-1.0, 1, -1), (-1.0, -1, 1))))
    box = Template("warmup_box", "warmup_box", trimesh.creation.box((0.06, 0.04, 0.02)), symmetry=flips, shape="box")
    bar = Template("warmup_bar", "warmup_bar", trimesh.creation.box((0.12, 0.02, 0.02)), symmetry=flips, shape="box")
    camera = Camera(np.array([[615.0, 0.0, 320.0], [0.0, 615.0, 240.0], [0.0, 0.0, 1.0]]), 640, 480)
    rng = np.random.default_rng(0)
    pose = make_pose(random_rotation(rng), [0.01, -0.02, 0.7])
    view = render_views(camera, [(box, pose)], rng)
    normpos = view.normpos[0]
    context = FitContext(camera, view.depth_m)
    fits = fit_many([normpos], [box], FitOptions(), context, workers=1)
    fits.append(fit_best(normpos, [box], FitOptions()))
    fits.append(fit_best(replace(normpos, label=""), [box, bar], FitOptions(), context))
    # a distorted camera's pose score (projection in numpy, its depth tests compiled apart from the pinhole one's)
    distorted = Camera(camera.K, camera.width, camera.height, np.array([0.01, 0.0, 0.0, 0.0, 0.0]))
    pts = np.asarray(normpos.points, dtype=np.float64)
    evaluate(
        prepare(box),
        np.asarray(np.linalg.inv(fits[0].frame_from_object), dtype=np.float64),
        1.0,
        pts,
        np.asarray(normpos.normals, dtype=np.float64),
        np.full(len(pts), 0.003),
        None,
        np.zeros(3),
        camera=distorted,
        depth_m=view.depth_m,
        camera_from_frame=np.eye(4),
    )
    seconds = time.perf_counter() - t0
    logger.info("fit kernels ready in %.1f s", seconds)
    return seconds, fits


EXAMPLES = Path(__file__).resolve().parents[1] / "examples" / "templates"


def prepare_builtin(examples: Path | None = EXAMPLES) -> dict[str, float]:
    """Prepare and store (on disk, `prepared.cache_dirs`) the built-in part library and the templates of the
    `examples` folder (default: the example templates shipped with the package); returns seconds per template."""
    from normpos_grasp.sim.parts import default_part_library
    from normpos_grasp.templates.library import load_library

    templates = list(default_part_library())
    if examples is not None and examples.is_dir():
        templates.extend(load_library(examples))
    out: dict[str, float] = {}
    for t in templates:
        t0 = time.perf_counter()
        prepare(t)
        out[t.name] = time.perf_counter() - t0
    logger.info("%d templates prepared and stored in %.1f s", len(out), sum(out.values()))
    return out


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    warm_up()
    prepare_builtin()
