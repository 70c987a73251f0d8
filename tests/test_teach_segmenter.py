"""`teach` extending the segmenter (issue 15 items 2-3): with a segmenter budget (seconds here) the taught library
gets LIBRARY/segmenter/normpos_seg.onnx + MODEL_CARD.md, a model that loads with the new class names, and every
command given `--library LIBRARY` uses it; a bad budget is one line, exit 2, nothing written; a failure in the
segmenter step leaves the library as it was. The part (tests/teach_parts.py) is built with trimesh here."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from normpos_grasp.cli.args import seg_model_from_args
from normpos_grasp.cli.main import build_parser, main
from normpos_grasp.errors import InputError
from normpos_grasp.perception.factory import ClassAgnostic, choose_segmenter, library_model
from normpos_grasp.perception.onnx_segmenter import BUNDLED_MODEL, OnnxSegmenter
from normpos_grasp.teach import TeachOptions, teach
from normpos_grasp.templates.library import load_library
from normpos_grasp.training import head_tune

sys.path.insert(0, str(Path(__file__).parent))
import teach_parts

TINY = TeachOptions(budget_s=8.0, rest_samples=400, max_poses=2, grasps_per_pose=1, trials=2, segmenter_budget_s=3.0)


@pytest.fixture(scope="module")
def lib(tmp_path_factory: pytest.TempPathFactory) -> Path:
    cad = tmp_path_factory.mktemp("cad")
    out = tmp_path_factory.mktemp("lib") / "my_parts"
    teach([teach_parts.write_part("t_profile", cad)], out, TINY)
    return out


def test_teach_stores_a_segmenter_that_knows_the_new_part(lib: Path) -> None:
    folder = lib / "segmenter"
    assert {p.name for p in folder.iterdir()} == {"normpos_seg.onnx", "MODEL_CARD.md"}
    assert not [p for p in lib.iterdir() if p.name.startswith(".")]  # no staging left behind
    model = OnnxSegmenter(folder / "normpos_seg.onnx")
    bundled = OnnxSegmenter(BUNDLED_MODEL).class_names
    assert model.class_names == [*bundled, "t_profile"] and model.weak_labels == ("t_profile",)
    assert "t_profile" in (folder / "MODEL_CARD.md").read_text()
    assert [t.name for t in load_library(lib)] == ["t_profile"]  # the segmenter folder is not a part


@pytest.mark.parametrize("command", ["estimate", "plan", "measure"])
def test_commands_given_the_library_use_its_segmenter(lib: Path, tmp_path: Path, command: str) -> None:
    model = lib / "segmenter" / "normpos_seg.onnx"
    parser = build_parser()
    base = {"estimate": ["estimate", str(tmp_path)], "measure": ["measure", str(tmp_path)],
            "plan": ["plan", str(tmp_path), "--im-id", "0", "--cell", "ur5e_bin_parallel"]}[command]  # fmt: skip
    out = ["--out", str(tmp_path / "o")]
    assert seg_model_from_args(parser.parse_args([*base, *out, "--library", "builtin", "--library", str(lib)])) == model
    other = tmp_path / "other.onnx"
    told = parser.parse_args([*base, *out, "--library", str(lib), "--seg-model", str(other)])
    assert seg_model_from_args(told) == other  # unless told otherwise
    assert seg_model_from_args(parser.parse_args([*base, *out, "--library", "builtin"])) is None  # the bundled one


def test_estimate_and_measure_load_the_librarys_segmenter(
    lib: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from normpos_grasp.perception import factory

    ds = tmp_path / "ds"
    code = main(["synth", "--out", str(ds), "--library", "builtin", "--library", str(lib), "--parts",
                 "t_profile,cube", "--scenes", "1", "--frames", "1", "--count", "3", "--resolution", "320x240",
                 "--no-progress"])  # fmt: skip
    assert code == 0
    loaded: list[object] = []
    real = factory._load_model
    monkeypatch.setattr(factory, "_load_model", lambda path: loaded.append(path) or real(path))
    scene = next(p for p in (ds / "train").iterdir() if p.is_dir())
    code = main(["estimate", str(ds / "train"), "--library", str(lib), "--library", "builtin", "--segmenter", "model",
                 "--out", str(tmp_path / "est.csv")])  # fmt: skip
    assert code == 0
    code = main(["measure", str(scene), "--library", str(lib), "--segmenter", "model", "--out", str(tmp_path / "m"),
                 "--no-ply"])  # fmt: skip
    assert code == 0
    assert loaded == [lib / "segmenter" / "normpos_seg.onnx"] * 2


def test_simulate_and_auto_take_the_librarys_segmenter(lib: Path) -> None:
    from normpos_grasp.simulate import episode

    seg = episode._segmenter("model", (str(lib), "builtin"))
    assert isinstance(seg, ClassAgnostic) and "t_profile" in seg.model.class_names  # weak label: whole library
    labels = {t.label for t in load_library(lib)} | {"cube"}
    choice = choose_segmenter("auto", library_model([lib]), labels)  # knows every label: no fallback to depth
    assert choice.kind == "model" and "t_profile" in choice.segmenter.model.class_names  # type: ignore[attr-defined]


@pytest.mark.parametrize("budget", ["-1", "nan", "500"])
def test_a_bad_segmenter_budget_is_one_line_and_writes_nothing(
    budget: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = teach_parts.write_part("hex_nut", tmp_path)
    out = tmp_path / "lib"
    code = main(["teach", str(path), "--out", str(out), "--segmenter-budget-min", budget, "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "--segmenter-budget-min" in err[0], err
    assert not out.exists()
    with pytest.raises(InputError, match="segmenter budget"):
        TeachOptions(segmenter_budget_s=-60.0)


def test_a_failed_segmenter_step_leaves_the_library_as_it_was(
    lib: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A fault while teaching the segmenter: the new part is not added and the segmenter taught before stays."""
    before = (lib / "segmenter" / "normpos_seg.onnx").read_bytes()

    def broken(*args: object, **kwargs: object) -> None:
        raise RuntimeError("out of memory")

    monkeypatch.setattr(head_tune, "tune_segmenter", broken)
    with pytest.raises(RuntimeError):
        teach([teach_parts.write_part("hex_nut", tmp_path)], lib, TINY)
    assert sorted(p.name for p in lib.iterdir()) == ["segmenter", "t_profile"]
    assert (lib / "segmenter" / "normpos_seg.onnx").read_bytes() == before


def test_a_part_named_like_the_segmenter_folder_is_refused(tmp_path: Path) -> None:
    path = teach_parts.write_part("t_profile", tmp_path)
    renamed = path.rename(tmp_path / "segmenter.stl")
    with pytest.raises(InputError, match="may not be named 'segmenter'"):
        teach([renamed], tmp_path / "lib", TINY)
    assert not (tmp_path / "lib").exists()
