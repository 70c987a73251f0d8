"""The CLI entry point: every command registers, errors become exit code 2 with one clear line."""

from __future__ import annotations

import pytest

from normpos_grasp.cli.main import COMMAND_MODULES, build_parser, main


def test_every_command_registers() -> None:
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    assert set(sub.choices) == {name.replace("_", "-") for name in COMMAND_MODULES}  # type: ignore[attr-defined]


def test_no_command_prints_help_and_fails(capsys: pytest.CaptureFixture[str]) -> None:
    assert main([]) == 2
    assert "usage: normpos-grasp" in capsys.readouterr().out


def test_library_error_is_one_line_and_exit_2(tmp_path, capsys: pytest.CaptureFixture[str]) -> None:  # type: ignore[no-untyped-def]
    missing = tmp_path / "nowhere.json"
    code = main(["execute", str(missing), "--robot", "127.0.0.1"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and err[0].startswith("normpos-grasp execute: error:")
    assert "Traceback" not in err[0]
