"""Stored template preparations: computed once, stored as plain npz arrays keyed by mesh + parameters + format,
loaded (no recomputation) equal to a fresh build, in the template folder or the user cache, validated and rebuilt
when missing, stale or damaged; the install-time warm-up stores the built-in ones."""

from __future__ import annotations

import dataclasses
import shutil
import zipfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import trimesh

from normpos_grasp.geometry import make_pose
from normpos_grasp.records.template import Symmetry, Template
from normpos_grasp.templates import prepared


@pytest.fixture(autouse=True)
def fresh_memory(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Iterator[None]:
    """Each test starts with empty in-memory caches and its own user cache folder."""
    monkeypatch.setenv(prepared.CACHE_ENV, str(tmp_path / "user_cache"))
    prepared._CACHE.clear()
    prepared._BY_KEY.clear()
    yield
    prepared._CACHE.clear()
    prepared._BY_KEY.clear()


def _forget() -> None:
    """What a fresh process starts with: nothing in memory."""
    prepared._CACHE.clear()
    prepared._BY_KEY.clear()


def _part(folder: Path | None, extents: tuple[float, float, float] = (0.05, 0.03, 0.02), **kw: object) -> Template:
    mesh = trimesh.creation.box(extents)
    src = ""
    if folder is not None:
        folder.mkdir(parents=True, exist_ok=True)
        src = str(folder)
    return Template("part", "part", mesh, source=src, shape="box", **kw)  # type: ignore[arg-type]


def _no_compute(monkeypatch: pytest.MonkeyPatch) -> None:
    def fail(mesh: object) -> dict[str, np.ndarray]:
        raise AssertionError("the preparation was recomputed")

    monkeypatch.setattr(prepared, "_compute", fail)


def _assert_same(a: prepared.PreparedTemplate, b: prepared.PreparedTemplate) -> None:
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if f.name in ("tree", "desc_tree"):
            np.testing.assert_array_equal(x.data, y.data)
        elif f.name == "bin_trees":
            for (tx, mx), (ty, my) in zip(x, y, strict=True):
                np.testing.assert_array_equal(mx, my)
                assert (tx is None) == (ty is None)
        elif isinstance(x, tuple):
            for u, v in zip(x, y, strict=True):
                assert np.asarray(u).dtype == np.asarray(v).dtype
                np.testing.assert_array_equal(u, v)
        elif isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and x.shape == y.shape, f.name
            np.testing.assert_array_equal(x, y)
        else:
            assert x == y, f.name


def test_stored_in_the_template_folder_and_loaded_equal_to_a_fresh_build(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    t = _part(tmp_path / "part")
    first = prepared.prepare(t)
    files = list((tmp_path / "part" / prepared.CACHE_FOLDER).glob("*.npz"))
    assert len(files) == 1 and files[0].name.startswith(prepared.cache_key(t)[:40])
    assert (tmp_path / "part" / prepared.CACHE_FOLDER / ".gitignore").read_text() == "*\n"
    assert not (tmp_path / "user_cache").exists()
    with np.load(files[0], allow_pickle=False) as data:  # plain arrays only: loads without pickle
        assert all(data[k].dtype != object for k in data.files)
    fresh = prepared._build(t)
    _assert_same(first, fresh)
    _forget()
    _no_compute(monkeypatch)
    again = prepared.prepare(_part(tmp_path / "part"))  # another process, another Template object
    _assert_same(again, fresh)


def test_no_folder_or_unwritable_folder_uses_the_user_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    procedural = _part(None)
    prepared.prepare(procedural)
    assert len(list((tmp_path / "user_cache").glob("*.npz"))) == 1
    blocked = tmp_path / "ro"
    blocked.mkdir()
    (blocked / prepared.CACHE_FOLDER).write_text("not a folder")  # the template folder cannot hold the cache
    other = _part(blocked, extents=(0.04, 0.04, 0.01))
    _forget()
    prepared.prepare(other)
    assert len(list((tmp_path / "user_cache").glob("*.npz"))) == 2
    _forget()
    _no_compute(monkeypatch)
    prepared.prepare(_part(blocked, extents=(0.04, 0.04, 0.01)))


def test_key_follows_mesh_parameters_and_format(monkeypatch: pytest.MonkeyPatch) -> None:
    a, b = _part(None), _part(None, extents=(0.05, 0.03, 0.021))
    flips = Symmetry(discrete=(make_pose(np.diag([1.0, -1.0, -1.0])),))
    assert prepared.cache_key(a) == prepared.cache_key(_part(None, symmetry=flips))  # symmetry applied after load
    assert prepared.cache_key(a) != prepared.cache_key(b)
    key = prepared.cache_key(a)
    monkeypatch.setattr(prepared, "FORMAT_VERSION", prepared.FORMAT_VERSION + 1)
    assert prepared.cache_key(a) != key
    monkeypatch.undo()
    monkeypatch.setattr(prepared, "GRID", prepared.GRID + 1)
    assert prepared.cache_key(a) != key


def test_same_mesh_shares_arrays_but_keeps_its_own_symmetry(monkeypatch: pytest.MonkeyPatch) -> None:
    plain = prepared.prepare(_part(None))
    _no_compute(monkeypatch)
    flips = Symmetry(discrete=(make_pose(np.diag([1.0, -1.0, -1.0])),))
    sym = prepared.prepare(_part(None, symmetry=flips))
    assert sym.samples is plain.samples  # shared in memory, not recomputed
    assert plain.sym.shape == (1, 4, 4) and sym.sym.shape == (2, 4, 4)


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory) -> tuple[prepared.PreparedTemplate, bytes]:
    """A fresh build of `_part`'s mesh and the bytes of its stored preparation (made once for the module)."""
    folder = tmp_path_factory.mktemp("reference") / "part"
    t = _part(folder)
    good = prepared._build(t)
    arrays = prepared._compute(t.mesh)
    path = folder / "stored.npz"
    assert prepared._store(path, prepared.cache_key(t), arrays)
    return good, path.read_bytes()


def _stored(tmp_path: Path, data: bytes) -> tuple[Template, Path]:
    t = _part(tmp_path / "part")
    path = tmp_path / "part" / prepared.CACHE_FOLDER / f"{prepared.cache_key(t)[:40]}.npz"
    path.parent.mkdir()
    path.write_bytes(data)
    return t, path


def _rewrite(path: Path, change: dict[str, np.ndarray | None]) -> None:
    with np.load(path, allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}
    for k, v in change.items():
        if v is None:
            arrays.pop(k)
        else:
            arrays[k] = v
    np.savez(path, **arrays)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    "damage",
    ["none", "truncated", "not_a_zip", "wrong_key", "dtype", "shape", "index", "nan", "missing", "pickled"],
)
def test_damaged_or_stale_file_is_rebuilt(
    tmp_path: Path, damage: str, reference: tuple[prepared.PreparedTemplate, bytes], monkeypatch: pytest.MonkeyPatch
) -> None:
    good, data_bytes = reference
    t, path = _stored(tmp_path, data_bytes)
    if damage == "none":  # the intact file is used as it is
        _no_compute(monkeypatch)
        _assert_same(prepared.prepare(t), good)
        return
    with np.load(path, allow_pickle=False) as data:
        samples, cells = data["samples"], data["cells"]
    if damage == "truncated":
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    elif damage == "not_a_zip":
        path.write_bytes(b"\x93NUMPY garbage")
    elif damage == "wrong_key":
        _rewrite(path, {"key": np.array("0" * 64)})
    elif damage == "dtype":
        _rewrite(path, {"samples": samples.astype(np.float32)})
    elif damage == "shape":
        _rewrite(path, {"cells": cells[:-1]})
    elif damage == "index":
        bad = cells.copy()
        bad[0, 0, 0, 0] = len(samples) + 5
        _rewrite(path, {"cells": bad})
    elif damage == "nan":
        bad_s = samples.copy()
        bad_s[3, 1] = np.nan
        _rewrite(path, {"samples": bad_s})
    elif damage == "missing":
        _rewrite(path, {"desc": None})
    elif damage == "pickled":
        _rewrite(path, {"desc": np.array([{"x": 1}], dtype=object)})
    before = path.read_bytes()
    again = prepared.prepare(_part(tmp_path / "part"))
    _assert_same(again, good)
    assert path.read_bytes() != before  # rewritten with a good copy
    with np.load(path, allow_pickle=False) as data:
        assert str(data["key"]) == prepared.cache_key(t)
        np.testing.assert_array_equal(data["samples"], samples)


def test_cache_off_writes_nothing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(prepared.CACHE_ENV, "off")
    prepared.prepare(_part(tmp_path / "part"))
    assert not (tmp_path / "part" / prepared.CACHE_FOLDER).exists()
    assert prepared.cache_dirs(_part(tmp_path / "part")) == []
    _forget()
    prepared.prepare(_part(tmp_path / "part"), persist=False)
    assert not (tmp_path / "part" / prepared.CACHE_FOLDER).exists()


def test_no_temporary_files_are_left(tmp_path: Path) -> None:
    prepared.prepare(_part(tmp_path / "part"))
    leftovers = [p.name for p in (tmp_path / "part" / prepared.CACHE_FOLDER).iterdir() if p.name.startswith(".tmp")]
    assert not leftovers
    assert zipfile.is_zipfile(next((tmp_path / "part" / prepared.CACHE_FOLDER).glob("*.npz")))


@pytest.mark.slow
def test_warm_up_stores_the_built_in_templates(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`prepare_builtin` (run by the install) stores every built-in part and example template; a later process
    only loads them."""
    from normpos_grasp.sim.parts import default_part_library
    from normpos_grasp.templates.library import load_library
    from normpos_grasp.templates.warmup import EXAMPLES, prepare_builtin

    examples = tmp_path / "examples"
    shutil.copytree(EXAMPLES, examples, ignore=shutil.ignore_patterns(prepared.CACHE_FOLDER))
    seconds = prepare_builtin(examples)
    lib = default_part_library()
    assert set(seconds) == {t.name for t in lib} | {"cube_40mm", "l_bracket"}
    stored = {p.name[:40] for p in (tmp_path / "user_cache").glob("*.npz")}
    assert stored == {prepared.cache_key(t)[:40] for t in lib}
    for name in ("cube_40mm", "l_bracket"):  # next to their template files
        assert len(list((examples / name / prepared.CACHE_FOLDER).glob("*.npz"))) == 1
    _forget()
    _no_compute(monkeypatch)
    for t in [*default_part_library(), *load_library(examples)]:
        prepared.prepare(t)
