"""Bad input, driven by a table (issue 20): every row is one class of defect a careless or unlucky user produces.

Each row builds a defective input from the project's own synth output (or a small file in tmp_path), runs the
CLI through `main([...])` and requires exit code 2, exactly one line `normpos-grasp CMD: error: ...` on stderr,
no traceback and nothing written under --out (an existing --out keeps its bytes). A new command inherits the
checks by adding rows. Also here: the atomic writer, the live view's Host check and timeouts, the loopback
parser, open-mesh repair without networkx, and the internal-error path (exit 3 + log file).
"""

from __future__ import annotations

import hashlib
import json
import re
import shutil
import socket
import struct
import subprocess
import sys
import time
import urllib.request
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest

from normpos_grasp.atomic import atomic_open, atomic_write_bytes
from normpos_grasp.cli.main import main
from normpos_grasp.errors import DatasetError
from normpos_grasp.hosts import host_header_is_loopback, is_loopback
from normpos_grasp.io.bop import BopScene

ERROR_LINE = re.compile(r"^normpos-grasp [a-z-]+( [a-z-]+)?: error: \S")


# -------------------------------------------------------------------------------------------------------------
# the base dataset: one synthetic scene, written once per module
# -------------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def base_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from normpos_grasp.sim.dataset import write_bop_dataset
    from normpos_grasp.sim.scene import SceneOptions

    root = tmp_path_factory.mktemp("bad_input") / "ds"
    write_bop_dataset(
        root, 1, 1, sensor="d435", resolution=(160, 120), parts=["cube", "box"], seed=3,
        scene_options=SceneOptions(count=3),
    )  # fmt: skip
    return root


@dataclass
class Case:
    """Paths of one row's private copy of the dataset; `out` is where the command must write nothing."""

    root: Path
    tmp: Path

    @property
    def scene(self) -> Path:
        return self.root / "train" / "000000"

    @property
    def split(self) -> Path:
        return self.root / "train"

    @property
    def models(self) -> Path:
        return self.root / "models"

    @property
    def out(self) -> Path:
        return self.tmp / "out"

    # -- mutations --------------------------------------------------------------------------------------------
    def camera_entry(self, **changes: object) -> None:
        path = self.scene / "scene_camera.json"
        table = json.loads(path.read_text())
        for key, value in changes.items():
            if value is _DELETE:
                del table["0"][key]
            else:
                table["0"][key] = value
        path.write_text(json.dumps(table))  # json writes inf as the literal Infinity

    def write_file(self, name: str, text: str) -> None:
        (self.scene / name).write_text(text)

    def write_depth(self, raw: np.ndarray) -> None:
        ok, buf = cv2.imencode(".png", raw)
        assert ok
        (self.scene / "depth" / "000000.png").write_bytes(buf.tobytes())

    def raw_depth(self) -> np.ndarray:
        img = cv2.imread(str(self.scene / "depth" / "000000.png"), cv2.IMREAD_UNCHANGED)
        assert img is not None and img.dtype == np.uint16
        return np.asarray(img)

    def patch_png_size(self, path: Path, width: int, height: int) -> None:
        data = bytearray(path.read_bytes())
        data[16:24] = struct.pack(">II", width, height)
        path.write_bytes(bytes(data))


_DELETE = object()


def _saturate(c: Case) -> None:
    raw = c.raw_depth()
    raw[raw > 0] = 65535
    c.write_depth(raw)


def _too_far(c: Case) -> None:
    c.camera_entry(depth_scale=1.0)  # raw units of 0.1 mm read as mm: the bin appears 10x farther, beyond 10 m
    raw = c.raw_depth()
    raw[raw > 0] = 15000
    c.write_depth(raw)


def _eight_bit(c: Case) -> None:
    c.write_depth((c.raw_depth() // 256).astype(np.uint8))


def _zero_depth(c: Case) -> None:
    c.write_depth(np.zeros_like(c.raw_depth()))


def _corrupt_rgb(c: Case) -> None:
    path = c.scene / "rgb" / "000000.png"
    data = path.read_bytes()
    path.write_bytes(data[:40] + bytes(len(data) - 40))  # a valid header, garbage pixels


def _interrupted_scene(c: Case) -> None:
    (c.scene / "scene_camera.json").write_text("{}\n")
    (c.root / "camera.json").unlink()
    (c.root / "parts.json").unlink()


def _no_dataset_camera(c: Case) -> None:
    (c.root / "camera.json").unlink()


def _models_info(c: Case, **changes: object) -> None:
    path = c.models / "models_info.json"
    info = json.loads(path.read_text())
    info["1"].update(changes)
    path.write_text(json.dumps(info))


def _corrupt_mesh(c: Case) -> None:
    (c.models / "obj_000001.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99\n" + bytes(7))


def _nan_mesh(c: Case) -> None:
    import trimesh

    mesh = trimesh.creation.box(extents=[40.0, 40.0, 40.0])
    mesh.vertices[0] = [np.nan, 0.0, 0.0]
    (c.models / "obj_000001.ply").write_bytes(mesh.export(file_type="ply"))


def _truncated_depth(c: Case) -> None:
    path = c.scene / "depth" / "000000.png"
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def _truncated_jpeg_rgb(c: Case) -> None:
    rgb = cv2.imread(str(c.scene / "rgb" / "000000.png"))
    assert rgb is not None
    (c.scene / "rgb" / "000000.png").unlink()
    ok, buf = cv2.imencode(".jpg", rgb)
    assert ok
    (c.scene / "rgb" / "000000.jpg").write_bytes(buf.tobytes()[:-200])


def _small_rgb(c: Case) -> None:
    cv2.imwrite(str(c.scene / "rgb" / "000000.png"), np.zeros((60, 80, 3), np.uint8))


def _interrupted_later_scene(c: Case) -> None:
    """Scene 1 of 2 stopped after its first frame: it lists frames but has no scene_static.json yet."""
    shutil.copytree(c.scene, c.split / "000001")
    (c.split / "000001" / "scene_static.json").unlink()
    (c.root / "camera.json").unlink()
    (c.root / "parts.json").unlink()


def _existing_file(c: Case) -> None:
    c.out.write_bytes(b"precious\n")


def _earlier_run(c: Case) -> None:
    (c.out / "000000").mkdir(parents=True)
    (c.out / "000000" / "000000.json").write_text('{"earlier": true}\n')


def _latin1_csv(c: Case) -> None:
    from normpos_grasp.camera.model import Camera

    Camera(np.array([[150.0, 0, 80.0], [0, 150.0, 60.0], [0, 0, 1]]), 160, 120).save_json(c.tmp / "camera.json")
    (c.tmp / "points.csv").write_bytes("name,x,y,z,u,v\nb\xe9ton,0,0,0,10,10\n".encode("latin-1"))


@dataclass(frozen=True)
class Row:
    """One class of bad input: `prepare` damages the copy, `argv` builds the command line, `match` is in the
    error line."""

    name: str
    prepare: Callable[[Case], None]
    argv: Callable[[Case], list[str]]
    match: str


def _measure(c: Case, *extra: str) -> list[str]:
    return ["measure", str(c.scene), "--out", str(c.out), *extra]


def _estimate(c: Case, *extra: str) -> list[str]:
    return ["estimate", str(c.split), "--models", str(c.models), "--out", str(c.out), "--segmenter", "gt", *extra]


def _synth(c: Case, *extra: str) -> list[str]:
    return ["synth", "--out", str(c.out), "--no-progress", "--resolution", "64x48", "--count", "1", *extra]


def _nothing(c: Case) -> None:
    return None


ROWS = [
    # scene_camera.json: shapes, types, finite values, ranges
    Row("cam_K short", lambda c: c.camera_entry(cam_K=[150.0, 0, 80.0, 0, 150.0, 60.0, 0, 0]), _measure, "cam_K"),
    Row("cam_K non-numeric", lambda c: c.camera_entry(cam_K=["fx", 0, 80, 0, 150, 60, 0, 0, 1]), _measure, "cam_K"),
    Row(
        "cam_K negative focal",
        lambda c: c.camera_entry(cam_K=[-150.0, 0, 80, 0, 150, 60, 0, 0, 1]),
        _measure,
        "fx, fy > 0",
    ),  # fmt: skip
    Row("cam_R_w2c short", lambda c: c.camera_entry(cam_R_w2c=[1.0, 0, 0, 0, 1, 0]), _measure, "cam_R_w2c"),
    Row(
        "cam_R_w2c scaled x1000",
        lambda c: c.camera_entry(cam_R_w2c=[1000.0, 0, 0, 0, 1000, 0, 0, 0, 1000]),
        _measure,
        "not a rotation",
    ),  # fmt: skip
    Row("cam_t_w2c NaN", lambda c: c.camera_entry(cam_t_w2c=[float("nan"), 0.0, 0.0]), _measure, "NaN"),
    Row("depth_scale string", lambda c: c.camera_entry(depth_scale="0.1"), _measure, "depth_scale"),
    Row("depth_scale missing", lambda c: c.camera_entry(depth_scale=_DELETE), _measure, "depth_scale is missing"),
    Row("depth_scale Infinity", lambda c: c.camera_entry(depth_scale=float("inf")), _measure, "depth_scale"),
    Row("depth_scale zero", lambda c: c.camera_entry(depth_scale=0), _measure, "depth_scale"),
    Row("depth_scale negative", lambda c: c.camera_entry(depth_scale=-0.1), _measure, "depth_scale"),
    Row(
        "scene_camera.json a list",
        lambda c: c.write_file("scene_camera.json", "[1, 2]"),
        _measure,
        "keyed by image id",
    ),  # fmt: skip
    # images: declared size, bit depth, plausible values
    Row(
        "depth PNG header 60000x60000",
        lambda c: c.patch_png_size(c.scene / "depth" / "000000.png", 60000, 60000),
        _measure,
        "60000x60000",
    ),  # fmt: skip
    Row(
        "rgb PNG header 60000x60000",
        lambda c: c.patch_png_size(c.scene / "rgb" / "000000.png", 60000, 60000),
        _measure,
        "60000x60000",
    ),  # fmt: skip
    Row("8-bit depth PNG", _eight_bit, _measure, "8-bit"),
    Row("saturated depth 65535", _saturate, _measure, "saturated"),
    Row("depth beyond 10 m", _too_far, _measure, "beyond 10 m"),
    Row("all-zero depth", _zero_depth, _measure, "no valid depth"),
    Row("corrupt rgb", _corrupt_rgb, _measure, "cannot decode"),
    Row("truncated depth PNG", _truncated_depth, _measure, "truncated"),
    Row("truncated rgb JPEG", _truncated_jpeg_rgb, _measure, "truncated"),
    Row("rgb and depth sizes differ", _small_rgb, _measure, "80x60"),
    Row("depth_scale 1e-30", lambda c: c.camera_entry(depth_scale=1e-30), _measure, "depth_scale"),
    Row(
        "cam_K focal 1e-6 px",
        lambda c: c.camera_entry(cam_K=[1e-6, 0, 80.0, 0, 1e-6, 60.0, 0, 0, 1]),
        _measure,
        "implausible",
    ),  # fmt: skip
    # interrupted synth datasets
    Row("interrupted synth: empty scene_camera.json", _interrupted_scene, _measure, "incomplete"),
    Row("interrupted synth: no camera.json", _no_dataset_camera, _measure, "incomplete"),
    Row(
        "interrupted synth: later scene partial",
        _interrupted_later_scene,
        lambda c: ["measure", str(c.split), "--out", str(c.out)],
        "incomplete",
    ),  # fmt: skip
    # output paths and earlier runs
    Row("measure --out is a file", _existing_file, _measure, "existing file"),
    Row("measure --out holds an earlier run", _earlier_run, _measure, "--overwrite"),
    Row("estimate --out is a folder", lambda c: c.out.mkdir(), _estimate, "is a folder"),
    Row("estimate --out exists", _existing_file, _estimate, "--overwrite"),
    Row("synth --out is a file", _existing_file, _synth, "existing file"),
    Row("synth --out holds files", _earlier_run, _synth, "--overwrite"),
    # bounded numbers
    Row("measure --half-window 100000", _nothing, lambda c: _measure(c, "--half-window", "100000"), "0..50"),
    Row("measure --erode -1", _nothing, lambda c: _measure(c, "--erode", "-1"), "0..100"),
    Row("synth --count 100000", _nothing, lambda c: _synth(c, "--count", "100000"), "0..100"),
    Row(
        "synth --resolution 100000x100000", _nothing, lambda c: _synth(c, "--resolution", "100000x100000"), "16..4096"
    ),  # fmt: skip
    Row("synth --scenes 0", _nothing, lambda c: _synth(c, "--scenes", "0"), "1..10000"),
    Row("estimate --max-frames -1", _nothing, lambda c: _estimate(c, "--max-frames", "-1"), "0..1000000"),
    Row("estimate --depth-bias-mm nan", _nothing, lambda c: _estimate(c, "--depth-bias-mm", "nan"), "mm"),
    # bad scenes and models through estimate: no header-only CSV
    Row("estimate on a short cam_K", lambda c: c.camera_entry(cam_K=[1.0, 2.0]), _estimate, "cam_K"),
    Row("estimate on all-zero depth", _zero_depth, _estimate, "no valid depth"),
    Row("negative model diameter", lambda c: _models_info(c, diameter=-5.0), _estimate, "diameter"),
    Row("corrupt model mesh", _corrupt_mesh, _estimate, "obj_000001"),
    Row("model mesh with NaN vertices", _nan_mesh, _estimate, "NaN"),
    # a CSV that is not UTF-8
    Row(
        "points CSV not UTF-8",
        _latin1_csv,
        lambda c: [
            "calibrate",
            "extrinsics",
            "--camera",
            str(c.tmp / "camera.json"),
            "--points",
            str(c.tmp / "points.csv"),
            "--out",
            str(c.out),
        ],
        "UTF-8",
    ),  # fmt: skip
]


def _snapshot(path: Path) -> dict[str, str]:
    if not path.exists():
        return {}
    if path.is_file():
        return {".": hashlib.sha256(path.read_bytes()).hexdigest()}
    return {str(p.relative_to(path)): hashlib.sha256(p.read_bytes()).hexdigest() for p in path.rglob("*")
            if p.is_file()}  # fmt: skip


@pytest.mark.parametrize("row", ROWS, ids=[r.name for r in ROWS])
def test_bad_input_gives_one_line_and_exit_2(
    row: Row, base_dataset: Path, tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    case = Case(tmp_path / "ds", tmp_path)
    shutil.copytree(base_dataset, case.root)
    row.prepare(case)
    before = _snapshot(case.out)
    capfd.readouterr()
    code = main(row.argv(case))
    captured = capfd.readouterr()  # file-descriptor level: codec libraries printing to stderr count too
    lines = captured.err.strip().splitlines()
    assert code == 2, captured.err
    assert len(lines) == 1, captured.err
    assert ERROR_LINE.match(lines[0]), lines[0]
    assert row.match in lines[0], lines[0]
    assert "Traceback" not in captured.err + captured.out
    assert _snapshot(case.out) == before  # nothing written (an existing --out keeps its bytes)
    leftovers = [p.name for p in tmp_path.iterdir() if p.name.startswith(".out")]
    assert not leftovers, leftovers  # no staging or temporary files next to --out


def test_every_class_of_issue_20_has_a_row() -> None:
    names = " ".join(r.name for r in ROWS)
    for word in ("cam_K", "cam_R_w2c", "depth_scale", "a list", "60000x60000", "8-bit", "saturated", "10 m",
                 "all-zero", "corrupt rgb", "interrupted", "is a file", "earlier run", "--half-window",
                 "--count", "--resolution", "not UTF-8", "diameter", "mesh"):  # fmt: skip
        assert word in names, word


def test_the_base_dataset_itself_measures(
    base_dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The table's rows fail because of their defect only: the untouched copy measures, and --overwrite reruns."""
    out = tmp_path / "out"
    scene = base_dataset / "train" / "000000"
    assert main(["measure", str(scene), "--out", str(out)]) == 0
    summary = json.loads((out / "000000" / "000000.json").read_text())
    assert len(summary["objects"]) == 3
    assert main(["measure", str(scene), "--out", str(out)]) == 2  # an earlier run is kept ...
    assert main(["measure", str(scene), "--out", str(out), "--overwrite"]) == 0  # ... unless asked
    assert not [p for p in (out / "000000").iterdir() if p.name.startswith(".")]  # no temporary files left
    capsys.readouterr()


def test_a_synth_scene_copied_on_its_own_still_reads(base_dataset: Path, tmp_path: Path) -> None:
    """The interrupted-dataset check looks at the dataset around a scene; a scene taken out of it is complete."""
    alone = tmp_path / "scenes" / "000000"
    shutil.copytree(base_dataset / "train" / "000000", alone)
    frame = BopScene(alone).load_frame(0)
    assert frame.depth_m.max() > 0 and frame.camera.world_from_camera is not None


def test_a_few_saturated_pixels_are_masked_with_a_warning(
    base_dataset: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    case = Case(tmp_path / "ds", tmp_path)
    shutil.copytree(base_dataset, case.root)
    raw = case.raw_depth()
    raw[0, :10] = 65535  # 10 of 19200 pixels: below the refusal threshold
    case.write_depth(raw)
    depth = BopScene(case.scene).load_depth(0)
    assert np.all(depth[0, :10] == 0) and depth.max() < 10.0
    assert "saturated" in caplog.text


def test_missing_rgb_is_black_but_corrupt_rgb_is_refused(base_dataset: Path, tmp_path: Path) -> None:
    case = Case(tmp_path / "ds", tmp_path)
    shutil.copytree(base_dataset, case.root)
    (case.scene / "rgb" / "000000.png").unlink()
    assert int(BopScene(case.scene).load_frame(0).rgb.max()) == 0  # depth-only scene
    shutil.copytree(base_dataset, tmp_path / "ds2")
    bad = Case(tmp_path / "ds2", tmp_path)
    _corrupt_rgb(bad)
    with pytest.raises(DatasetError, match="cannot decode"):
        BopScene(bad.scene).load_frame(0)


def test_subprocess_error_is_one_line_without_traceback(base_dataset: Path, tmp_path: Path) -> None:
    """The installed entry point, not only main(): logging and interpreter shutdown add nothing to stderr."""
    case = Case(tmp_path / "ds", tmp_path)
    shutil.copytree(base_dataset, case.root)
    case.camera_entry(depth_scale=float("inf"))
    proc = subprocess.run(
        [sys.executable, "-m", "normpos_grasp.cli.main", "measure", str(case.scene), "--out", str(case.out)],
        capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and ERROR_LINE.match(lines[0]), proc.stderr
    assert not case.out.exists()


def test_internal_error_exits_3_with_a_log_file(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import normpos_grasp.cli.measure as measure_cli

    def broken(args: object) -> int:
        raise ZeroDivisionError("a bug")

    monkeypatch.setattr(measure_cli, "run", broken)
    monkeypatch.setenv("NORMPOS_GRASP_LOG_DIR", str(tmp_path / "logs"))
    code = main(["measure", str(tmp_path), "--out", str(tmp_path / "o")])
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 3 and len(lines) == 1, lines
    assert "internal error: ZeroDivisionError: a bug" in lines[0]
    logs = list((tmp_path / "logs").glob("crash-*.log"))
    assert len(logs) == 1 and lines[0].count(str(logs[0])) == 1
    assert "Traceback" in logs[0].read_text() and "ZeroDivisionError" in logs[0].read_text()


# -------------------------------------------------------------------------------------------------------------
# atomic writer
# -------------------------------------------------------------------------------------------------------------
def test_atomic_writer_keeps_the_old_file_when_writing_fails(tmp_path: Path) -> None:
    target = tmp_path / "frame.json"
    target.write_text("old complete content\n")
    with pytest.raises(RuntimeError, match="disk pulled"), atomic_open(target, "w") as fh:
        fh.write('{"half": ')
        raise RuntimeError("disk pulled")
    assert target.read_text() == "old complete content\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frame.json"]  # the temporary file is gone
    atomic_write_bytes(target, b"new\n")
    assert target.read_bytes() == b"new\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frame.json"]


def test_atomic_writer_never_shows_a_partial_file(tmp_path: Path) -> None:
    target = tmp_path / "points.bin"
    with atomic_open(target, "wb") as fh:
        fh.write(b"x" * 1000)
        assert not target.exists()  # readers see nothing until the file is complete
    assert target.stat().st_size == 1000


def test_atomic_writer_file_mode_follows_umask(tmp_path: Path) -> None:
    import os

    old = os.umask(0o022)
    try:
        atomic_write_bytes(tmp_path / "a", b"1")
    finally:
        os.umask(old)
    assert (tmp_path / "a").stat().st_mode & 0o777 == 0o644


# -------------------------------------------------------------------------------------------------------------
# loopback parsing and the live view
# -------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("host", "ok"),
    [("127.0.0.1", True), ("127.3.2.1", True), ("::1", True), ("[::1]", True), ("localhost", True),
     ("LocalHost.", True), ("::ffff:127.0.0.1", True), ("127.0.0.1.nip.io", False), ("127.evil.com", False),
     ("0.0.0.0", False), ("10.0.0.1", False), ("", False), ("0x7f000001", False), ("2130706433", False),
     ("localhost.evil.com", False)],
)  # fmt: skip
def test_is_loopback_parses_instead_of_prefix_matching(host: str, ok: bool) -> None:
    assert is_loopback(host) is ok


@pytest.mark.parametrize(
    ("header", "ok"),
    [("127.0.0.1:8765", True), ("localhost", True), ("localhost:80", True), ("[::1]:8080", True),
     ("evil.example", False), ("evil.example:8765", False), ("127.0.0.1.nip.io:8765", False), ("", False),
     (None, False), ("127.0.0.1:0", False), ("127.0.0.1:70000", False), ("127.0.0.1:x", False),
     ("::1", False), ("127.0.0.1 evil", False)],
)  # fmt: skip
def test_host_header_check(header: str | None, ok: bool) -> None:
    assert host_header_is_loopback(header) is ok


def _raw_request(port: int, host_header: str) -> bytes:
    with socket.create_connection(("127.0.0.1", port), timeout=10) as sock:
        sock.sendall(f"GET /scene.json HTTP/1.1\r\nHost: {host_header}\r\nConnection: close\r\n\r\n".encode())
        chunks = []
        while chunk := sock.recv(65536):
            chunks.append(chunk)
    return b"".join(chunks)


def test_live_view_refuses_foreign_host_headers() -> None:
    from normpos_grasp.report.live import LiveView

    with LiveView(port=0) as view:
        port = int(view.url.rsplit(":", 1)[1].strip("/"))
        assert _raw_request(port, "evil.example").startswith(b"HTTP/1.0 403")
        assert _raw_request(port, f"127.0.0.1.nip.io:{port}").startswith(b"HTTP/1.0 403")
        assert _raw_request(port, f"127.0.0.1:{port}").startswith(b"HTTP/1.0 200")
        assert _raw_request(port, f"localhost:{port}").startswith(b"HTTP/1.0 200")
        with urllib.request.urlopen(view.url + "scene.json", timeout=10) as resp:  # a browser's request
            assert resp.status == 200


def test_live_view_drops_slow_clients_and_caps_connections() -> None:
    from normpos_grasp.report.live import LiveView

    with LiveView(port=0, request_timeout_s=0.5, max_connections=2) as view:
        port = int(view.url.rsplit(":", 1)[1].strip("/"))
        slow = socket.create_connection(("127.0.0.1", port), timeout=10)
        slow.sendall(b"GET / HTTP/1.1\r\n")  # and never finishes the request
        other = socket.create_connection(("127.0.0.1", port), timeout=10)  # the second slot
        third = socket.create_connection(("127.0.0.1", port), timeout=10)
        assert third.recv(100).startswith(b"HTTP/1.0 503")  # the cap: answered at once, not queued
        third.close()
        t0 = time.monotonic()
        assert slow.recv(100) == b""  # the half-open request is dropped after the timeout ...
        assert time.monotonic() - t0 < 5.0
        # ... also when it dribbles one byte at a time (the deadline covers the whole request)
        other.sendall(b"G")
        t0 = time.monotonic()
        for _ in range(20):
            try:
                other.sendall(b"E")
            except OSError:
                break
            if time.monotonic() - t0 > 1.5:
                break
            time.sleep(0.1)
        other.settimeout(5.0)
        try:
            rest = other.recv(100)
        except ConnectionResetError:
            rest = b""
        assert rest == b"" and time.monotonic() - t0 < 5.0
        slow.close()
        other.close()
        assert _raw_request(port, f"127.0.0.1:{port}").startswith(b"HTTP/1.0 200")  # slots were released


def test_live_view_binds_loopback_only() -> None:
    from normpos_grasp.errors import InputError
    from normpos_grasp.report.live import LiveView

    with pytest.raises(InputError, match="loopback"):
        LiveView(host="0.0.0.0", port=0)


# -------------------------------------------------------------------------------------------------------------
# open meshes: repaired without networkx (trimesh.repair needs it; it is not needed on this path)
# -------------------------------------------------------------------------------------------------------------
def test_open_mesh_is_repaired_without_networkx(monkeypatch: pytest.MonkeyPatch) -> None:
    import trimesh

    from normpos_grasp.templates.mesh_check import check_mesh

    monkeypatch.setitem(sys.modules, "networkx", None)  # `import networkx` fails as if it were not installed
    box = trimesh.creation.box(extents=[0.05, 0.04, 0.03])
    open_box = trimesh.Trimesh(box.vertices, box.faces[1:], process=False)
    assert not open_box.is_watertight
    repaired, report = check_mesh(open_box, "open box")
    assert report.watertight and report.ok and "filled holes" in report.repairs
    assert repaired.volume == pytest.approx(box.volume, rel=1e-9)
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.03)
    faces = sphere.faces.copy()
    faces[::3] = faces[::3, ::-1]
    wound, report = check_mesh(trimesh.Trimesh(sphere.vertices, faces, process=False), "mixed winding")
    assert report.winding_consistent and report.ok
    assert wound.volume == pytest.approx(sphere.volume, rel=1e-9)


@pytest.mark.parametrize("host", ["127.0.0.1.nip.io", "localhost", "::1", "10.0.0.1", "127.1", ""])
def test_the_emulator_binds_only_an_ipv4_loopback_literal(host: str) -> None:
    """A string prefix is no address check: names that resolve elsewhere, short forms and other nets are refused."""
    from normpos_grasp.errors import InputError
    from normpos_grasp.hosts import is_ipv4_loopback_literal
    from normpos_grasp.sim.ur_emulator.process import EmulatorProcess

    assert not is_ipv4_loopback_literal(host)
    with pytest.raises(InputError, match="loopback"):
        EmulatorProcess(host, "ur5e")
    assert is_ipv4_loopback_literal("127.0.0.42") and is_ipv4_loopback_literal("127.0.0.1")


def test_simulate_refuses_an_unknown_gripper_before_writing(tmp_path: Path) -> None:
    """`--gripper bogus` was silently ignored (the cell's tool was simulated): now one line, exit 2, nothing written.
    The packaged cell name is accepted like a path."""
    out = tmp_path / "run"
    proc = subprocess.run(
        [sys.executable, "-m", "normpos_grasp.cli.main", "simulate", "--cell", "ur5e_bin_parallel", "--scenes", "1",
         "--out", str(out), "--gripper", "bogus", "--no-progress"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, proc.stderr
    assert len(lines) == 1 and "unknown gripper 'bogus'" in lines[0] and "2f85" in lines[0]
    assert not out.exists()
