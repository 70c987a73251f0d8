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


def test_no_numeric_option_of_any_command_takes_nan_or_inf() -> None:
    """Every option that parses a number refuses nan and inf at the command line (exit 2 there), so no command
    can run with a NaN cap, tolerance or duration; a new command's options inherit the check."""
    import argparse
    import math

    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    accepted = []
    numeric = 0
    for name, command in sub.choices.items():
        for action in command._actions:
            if not action.option_strings or action.type is None or not callable(action.type):
                continue
            try:
                sample = action.type("1")
            except (argparse.ArgumentTypeError, ValueError, TypeError):
                sample = None
            if not isinstance(sample, int | float):
                continue  # paths, names, WxH sizes
            numeric += 1
            for text in ("nan", "inf", "-inf", "1e400"):
                try:
                    value = action.type(text)
                except (argparse.ArgumentTypeError, ValueError, TypeError):
                    continue
                if not math.isfinite(float(value)):
                    accepted.append(f"{name} {action.option_strings[0]} {text}")
    assert numeric > 20  # the walk found the numeric options
    assert not accepted, accepted


def test_execute_flags_tighten_a_cells_caps_and_never_loosen_them() -> None:
    """With a cell, --speed-fraction and --max-joint-accel are further caps (a first run on a real arm at 30 %),
    not ignored; a value above the cell's cap leaves the cell's."""
    import argparse

    import numpy as np

    from normpos_grasp.cell import resolve_cell
    from normpos_grasp.cli.execute import _tightened
    from normpos_grasp.execution import SafetyLimits

    cell = resolve_cell("ur5e_bin_parallel")
    base = SafetyLimits.from_cell(cell)
    slow = _tightened(base, argparse.Namespace(speed_fraction=0.3, max_joint_accel=1.0))
    assert np.all(slow.max_joint_speed <= 0.3 * np.pi + 1e-9) and np.all(slow.max_joint_accel == 1.0)
    same = _tightened(base, argparse.Namespace(speed_fraction=1.0, max_joint_accel=40.0))
    assert np.array_equal(same.max_joint_speed, base.max_joint_speed)
    assert np.array_equal(same.max_joint_accel, base.max_joint_accel)


@pytest.mark.parametrize(
    "argv",
    [
        ["synth", "--out", "{tmp}/ds", "--parts", ",,"],
        ["simulate", "--cell", "ur5e_bin_parallel", "--out", "{tmp}/sim", "--parts", " , "],
        ["demo", "--out", "{tmp}/demo", "--part-names", ","],
        ["demo", "--out", "{tmp}/demo", "--parts", "0"],
    ],
)
def test_a_part_list_that_names_nothing_is_refused(
    argv: list[str], tmp_path, capsys: pytest.CaptureFixture[str]
) -> None:  # type: ignore[no-untyped-def]
    """',,' (a script's empty variable) is not read as 'every part'; nothing is written."""
    assert main([a.format(tmp=tmp_path) for a in argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--part" in err[0]
    assert not any(tmp_path.iterdir())
