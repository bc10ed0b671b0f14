"""The typed hardware spec (``sim.sensors``): every figure of ``sim/data/hardware.toml`` typed and
checked, the gyro's figures read from it, and a bad file named in a one-line error."""
import math

import numpy as np
import pytest

from sim.sensors import HARDWARE_TOML, HardwareError, hardware_spec, load_hardware


def test_the_bundled_spec_holds_every_figure():
    from sim.camera import hardware

    spec = hardware_spec()
    raw = hardware()
    # the typed spec and the file agree figure for figure, and nothing in the file is left out
    assert spec.model_dump(mode="json") == {k: {f: (list(v) if isinstance(v, (list, tuple)) else v)
                                                for f, v in sec.items()} for k, sec in raw.items()}
    assert spec.d435i.width == 640 and len(spec.velodyne.vertical_deg) == 32
    assert spec.gyro.noise_density_deg_s_rthz == 0.014


def test_the_gyro_reads_its_figures_from_the_spec():
    from sim import imu

    g = hardware_spec().gyro
    assert imu.NOISE_DENSITY == math.radians(g.noise_density_deg_s_rthz)
    assert imu.BIAS_WALK == math.radians(g.bias_walk_deg_s_rts)
    # the default calibration is the spec's: the same readings as naming it
    a = imu.Gyro(np.random.default_rng(1))
    b = imu.Gyro(np.random.default_rng(1), calibration_s=g.calibration_s)
    assert a.bias == b.bias and a.measure(0.1, 0.1) == b.measure(0.1, 0.1)


@pytest.mark.parametrize("edit,expected", [
    (("fx = 610.0", "fx = -1.0"), r"\[d435i.fx\]: Input should be greater than 0"),
    (("range_noise = 0.01", "range_noise = 0.01\nrange_nosie = 0.02"), r"\[velodyne.range_nosie\]: Extra inputs"),
    (("calibration_s = 1.0", "calibration_s = \"one\""), r"\[gyro.calibration_s\]"),
])
def test_a_bad_figure_is_named(tmp_path, edit, expected):
    text = HARDWARE_TOML.read_text()
    assert edit[0] in text
    bad = tmp_path / "hardware.toml"
    bad.write_text(text.replace(edit[0], edit[1], 1))
    with pytest.raises(HardwareError, match=expected) as err:
        load_hardware(bad)
    assert str(bad) in str(err.value) and "\n" not in str(err.value)


def test_an_unreadable_file_is_named(tmp_path):
    with pytest.raises(HardwareError, match="missing.toml"):
        load_hardware(tmp_path / "missing.toml")
