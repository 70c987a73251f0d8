"""The segmenter taught new parts by a head refit on its frozen trunk (`training.head_tune`), and what the pipeline
does with the classes it learned (weak hints)."""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest
import trimesh

from normpos_grasp.perception.onnx_segmenter import BUNDLED_MODEL, OnnxSegmenter
from normpos_grasp.teach import check_cad
from normpos_grasp.training import head_tune

sys.path.insert(0, str(Path(__file__).parent))
import teach_parts


def test_lifted_heads_give_the_bundled_models_outputs(tmp_path: Path) -> None:
    """The 1x1 heads written back as 3x3 convolutions (weights on the centre tap): the model's outputs unchanged,
    so the window layout (channel, row, column) of `windows` and `write_model` agree with ONNX's."""
    import onnxruntime as ort

    trunk = head_tune.Trunk(BUNDLED_MODEL)
    lifted = head_tune.lift(trunk.base, 3)
    out = head_tune.write_model(BUNDLED_MODEL, lifted, trunk.names, (), 0.35, tmp_path / "m.onnx", {})
    x = np.random.default_rng(0).normal(size=(1, 4, *trunk.input_hw)).astype(np.float32)
    a = ort.InferenceSession(str(BUNDLED_MODEL), providers=["CPUExecutionProvider"]).run(None, {"images": x})
    b = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"]).run(None, {"images": x})
    assert np.allclose(a[0], b[0], atol=1e-4) and np.allclose(a[1], b[1])
    # the heads as matrices on the windows: the class logits of every cell reproduced from the features
    feats, _ = trunk.run(x)
    logits = head_tune.windows(feats, 3) @ lifted.cls.T
    assert np.allclose(1 / (1 + np.exp(-logits.T)), a[0][0, 4:12], atol=1e-4)


def test_a_head_refit_teaches_the_model_a_new_part(tmp_path: Path) -> None:
    """Bins of a T-profile (made here, unlike the built-in parts) mixed with built-in parts: the bundled model has
    no class for it; after the refit the model loads with the new class name (a weak label) and finds the
    T-profiles of its frames under that name; with `fit_known_classes=False` the built-in classes' rows are left as
    they were."""
    from normpos_grasp.cell import resolve_cell
    from normpos_grasp.templates.library import resolve_library
    from normpos_grasp.training.data import cell_samples
    from normpos_grasp.training.metrics import MatchStats

    tee = check_cad(teach_parts.write_part("t_profile", tmp_path))
    library = [tee, *resolve_library(["builtin"])]
    cell = resolve_cell("ur5e_bin_parallel")
    draw = ("t_profile",) * 4 + ("cube", "ring")
    samples = [s for seed in (11, 12, 13) for s in cell_samples(cell, seed, library=library, parts=draw)]
    trunk = head_tune.Trunk(BUNDLED_MODEL)
    names = [*trunk.names, "t_profile"]
    frames = [head_tune.frame_data(s, trunk, names, 1) for s in samples]
    opts = head_tune.HeadTuneOptions(kernel=1, cls_iterations=60, coef_iterations=30)
    heads = head_tune.fit_heads(frames, trunk.base, len(names), trunk.input_hw, trunk.stride, opts)
    frozen = replace(opts, cls_iterations=5, coef_iterations=1, fit_known_classes=False)
    kept = head_tune.fit_heads(frames, trunk.base, len(names), trunk.input_hw, trunk.stride, frozen)
    assert np.array_equal(kept.cls[: len(trunk.names)], trunk.base.cls)  # the built-in classes keep their rows
    assert np.abs(kept.cls[-1, :-1]).max() > 0  # the new class's row is fitted (it starts at zero weights)
    path = head_tune.write_model(BUNDLED_MODEL, heads, names, ["t_profile"], 0.3, tmp_path / "tuned.onnx", {"x": 1})
    model = OnnxSegmenter(path)
    assert model.class_names == names and model.weak_labels == ("t_profile",)
    assert json.loads(model.metadata[head_tune.TUNE_KEY]) == {"x": 1}
    stats = MatchStats()
    for s in samples:
        gt = [(g, v) for g, v in zip(s.instances, s.visib_fract, strict=True) if g.label == "t_profile"]
        pred = [p for p in model.segment(s.frame) if p.label == "t_profile"]
        stats.add(pred, [g for g, _ in gt], np.array([v for _, v in gt]))
    assert stats.gt >= 6 and stats.recall >= 0.6 and stats.precision >= 0.6, (stats.gt, stats.recall, stats.precision)


def test_a_refit_of_a_model_that_knows_every_label_is_refused(tmp_path: Path) -> None:
    from normpos_grasp.cell import resolve_cell
    from normpos_grasp.errors import InputError
    from normpos_grasp.templates.library import resolve_library

    with pytest.raises(InputError, match="already knows every label"):
        head_tune.tune_segmenter(list(resolve_library(["builtin"])), tmp_path, resolve_cell("ur5e_bin_parallel"))
    assert not any(tmp_path.iterdir())


def test_a_weak_class_lets_the_whole_library_compete(monkeypatch: pytest.MonkeyPatch) -> None:
    """A model whose 't_profile' class came from a head refit (`weak_labels`): its masks are class-agnostic even
    though it knows every label, and a mask it calls 't_profile' is fitted against the whole library, so a box it
    misnamed is fitted as the box (a sure class, 'box', still gets only the unknown and weak templates beside it)."""
    from normpos_grasp import pipeline
    from normpos_grasp.perception.factory import ClassAgnostic, for_library
    from normpos_grasp.records.template import Template, TemplateFit

    box = Template("box", "box", trimesh.creation.box((0.05, 0.03, 0.02)))
    tee = Template("t_profile", "t_profile", trimesh.creation.box((0.06, 0.03, 0.025)))
    seen: dict[int, list[str]] = {}
    scores = {"box": (0.90, True), "t_profile": (0.70, True)}

    def fake_fit_many(nps, lib, *args, **kwargs):  # type: ignore[no-untyped-def]
        out = []
        for n in nps:
            if n.label:
                cands = [t for t in lib if t.label == n.label]
            else:
                seen.setdefault(n.instance_id, []).extend(t.name for t in lib)
                cands = list(lib)
            best = max(cands, key=lambda t: scores[t.name][0])
            s, ok = scores[best.name]
            out.append(TemplateFit(best, np.eye(4), s, 0.001, 1.0, 1.0, 0.0, ok, instance_id=n.instance_id))
        return out

    monkeypatch.setattr(pipeline, "fit_many", fake_fit_many)

    class Model:
        class_names = ("box", "t_profile")
        weak_labels = ("t_profile",)

    seg = for_library(Model(), {"box", "t_profile"})  # type: ignore[arg-type]
    assert isinstance(seg, ClassAgnostic)
    seg.hints = {1: "t_profile", 2: "box"}

    @dataclass(frozen=True)
    class N:
        label: str
        instance_id: int

    fits = pipeline._fit_hinted([N("", 1), N("", 2)], [box, tee], seg, pipeline.PipelineOptions(), None)  # type: ignore[arg-type, list-item]
    assert sorted(seen[1]) == ["box", "t_profile"] and seen[2] == ["t_profile"]
    assert [f.template.name for f in fits] == ["box", "box"]
