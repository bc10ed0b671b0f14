"""``dopeslam odometry``'s command line and its one-line errors (the short simulated drive scored
against ground truth: ``tests/e2e/test_odometry_e2e.py``)."""


def test_command_line():
    from testbed.cli import build_parser
    from testbed.commands.odometry import run

    args = build_parser().parse_args(["odometry", "shelf_corridor", "--out", "d", "--seed", "3", "--duration", "5"])
    assert (args.scenario, args.out, args.seed, args.duration, args.func) == ("shelf_corridor", "d", 3, 5.0, run)


def test_settings_it_does_not_apply_and_a_bad_odometry_are_one_line_errors(tmp_path, capsys):
    from testbed.cli import main

    assert main(["odometry", "--out", str(tmp_path / "o"), "--set", "detector.stages=3"]) == 2
    err = capsys.readouterr().err.strip()
    assert "detector.stages" in err and "does not apply" in err and len(err.splitlines()) == 1
    assert main(["odometry", "--out", str(tmp_path / "o"), "--odometry", "no_such_module:Odo"]) == 2
    assert "no_such_module" in capsys.readouterr().err
    assert main(["odometry", "--out", str(tmp_path / "o"), "--set", "odometry.voxel_size_m=-1"]) == 2
    assert "odometry.voxel_size_m" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()  # nothing ran
