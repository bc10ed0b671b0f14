"""Property tests: whatever a user's file or option holds, the scenario model, the object-store
reader and the bag message decoders end in a valid result or one clear project error, never an
uncaught exception of another kind."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sim.scenario import ScenarioError, default_scenario_path, load_scenario, with_overrides
from stack.errors import DopeSlamError
from stack.io import strict_json
from stack.object_store import ObjectStoreError, read_objects

SETTINGS = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
numbers = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-10**12, 10**12))
values = st.one_of(numbers, st.text(max_size=8), st.booleans(), st.none(),
                   st.lists(numbers, max_size=4))
BASE = load_scenario(None)


@SETTINGS
@given(seed=st.one_of(st.none(), st.integers(-5, 10**20)),
       duration=st.one_of(st.none(), st.floats(allow_nan=True, allow_infinity=True)),
       light=st.one_of(st.none(), st.floats(allow_nan=True, allow_infinity=True)))
def test_overrides_are_valid_or_one_clear_error(seed, duration, light):
    try:
        sc = with_overrides(BASE, seed=seed, duration=duration, light=light)
    except ScenarioError as e:
        assert str(e).startswith("--") and "\n" not in str(e)
        return
    assert 0 < sc.duration <= 3600 and 0 <= sc.light <= 1 and sc.seed >= 0
    assert math.isfinite(sc.duration)


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if v is None:
        return '""'
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v == math.inf else "-inf" if v == -math.inf else repr(v))
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return json.dumps(v)


FIELDS = ["duration", "light", "seed", "physics_hz"]
TABLE_FIELDS = [("room", "size"), ("room", "wall_height"), ("robot", "start"), ("route", "speed"),
                ("sensors", "camera_rate"), ("sensors", "lidar_azimuth_steps")]


@SETTINGS
@given(top=st.dictionaries(st.sampled_from(FIELDS), values, max_size=2),
       table=st.dictionaries(st.sampled_from(TABLE_FIELDS), values, max_size=2))
def test_scenario_files_load_or_fail_with_file_and_field(tmp_path_factory, top, table):
    text = default_scenario_path().read_text()
    lines = text.splitlines()
    for key, v in top.items():
        lines = [f"{key} = {_toml_value(v)}" if ln.split("=")[0].strip() == key and not ln.startswith(" ") else ln
                 for ln in lines]
    out, section = [], None
    for ln in lines:
        if ln.startswith("["):
            section = ln.strip("[] ")
        key = ln.split("=")[0].strip()
        if (section, key) in table:
            ln = f"{key} = {_toml_value(table[(section, key)])}"
        out.append(ln)
    p = tmp_path_factory.mktemp("scene") / "scene.toml"
    p.write_text("\n".join(out) + "\n")
    try:
        sc = load_scenario(p)
    except ScenarioError as e:
        assert str(p) in str(e)
        return
    assert math.isfinite(sc.duration) and all(math.isfinite(v) for v in sc.robot.start)


@SETTINGS
@given(rows=st.lists(st.dictionaries(st.sampled_from(["id", "class", "x", "y", "z", "qx", "qy", "qz", "qw",
                                                       "size_x", "edited", "status", "observations", "score"]),
                                     values, max_size=14), max_size=3),
       extra=st.sampled_from(["", "garbage", "{", "[]", '{"objects": 3}']))
def test_store_reader_reads_or_names_file_row_and_column(tmp_path_factory, rows, extra):
    p = tmp_path_factory.mktemp("store") / "labels.json"
    doc = {"format": "dopeslam-object-store", "version": 1, "objects": rows}
    try:
        text = extra or strict_json(doc)
    except (TypeError, ValueError):
        return
    p.write_text(text)
    try:
        objects = read_objects(p)
    except ObjectStoreError as e:
        assert str(p) in str(e) and isinstance(e, DopeSlamError)
        return
    for o in objects:
        assert np.all(np.isfinite(o.xyz))


@SETTINGS
@given(encoding=st.sampled_from(["rgb8", "bgr8", "mono8", "16UC1", "32FC1", "yuv422", "bayer_rggb8", "", "rgba8"]),
       width=st.integers(0, 12), height=st.integers(0, 12), step_delta=st.integers(-4, 4),
       data_len=st.integers(0, 600))
def test_image_decoder_returns_pixels_or_a_clear_error(encoding, width, height, step_delta, data_len):
    from testbed.bags.convert import dialect, image_array

    d = dialect("ros2")
    msg = d.make("sensor_msgs/msg/Image", header=d.header(0, "cam"), height=height, width=width,
                 encoding=encoding, is_bigendian=0, step=max(0, width * 3 + step_delta),
                 data=np.zeros(data_len, dtype=np.uint8))
    try:
        arr = image_array(msg)
    except (ValueError, DopeSlamError) as e:
        assert str(e)
        return
    assert arr.shape[:2] == (height, width)


@SETTINGS
@given(n=st.integers(0, 50), point_step=st.integers(0, 24), data_len=st.integers(0, 800),
       offset=st.integers(0, 20), datatype=st.integers(0, 10))
def test_pointcloud_decoder_returns_arrays_or_a_clear_error(n, point_step, data_len, offset, datatype):
    from testbed.bags.convert import cloud_arrays, dialect

    d = dialect("ros2")
    fields = [d.make("sensor_msgs/msg/PointField", name=name, offset=offset + 4 * i, datatype=datatype, count=1)
              for i, name in enumerate("xyz")]
    msg = d.make("sensor_msgs/msg/PointCloud2", header=d.header(0, "velodyne"), height=1, width=n, fields=fields,
                 is_bigendian=False, point_step=point_step, row_step=point_step * n,
                 data=np.zeros(data_len, dtype=np.uint8), is_dense=True)
    try:
        arrays = cloud_arrays(msg)
    except (ValueError, DopeSlamError) as e:
        assert str(e)
        return
    assert all(len(a) == n for a in arrays.values())


@SETTINGS
@given(data=st.one_of(st.binary(max_size=64), st.text(max_size=64).map(lambda t: t.encode("utf-8")),
                      st.sampled_from([b"\xff\xfe[room]", b"[[scenarios]]\nscenario = 1", b"\x00" * 8,
                                       "caf\u00e9 = 1".encode("latin-1")])),
       kind=st.sampled_from(["scenario", "suite", "config.toml", "config.yaml", "config.json"]))
def test_any_bytes_in_a_user_file_load_or_fail_in_one_line(tmp_path_factory, data, kind):
    """A scenario, suite or config file holding any bytes (binary, not UTF-8, text that is not the
    format) loads or ends in one project error naming the file: never a UnicodeDecodeError or
    another exception that a command line would print as a traceback."""
    from stack.config import read_file
    from testbed.testing.suite import load_suite

    folder = tmp_path_factory.mktemp("user")
    path = folder / ("x.toml" if kind in ("scenario", "suite") else "x." + kind.split(".")[1])
    path.write_bytes(data)
    load = {"scenario": load_scenario, "suite": load_suite}.get(kind, read_file)
    try:
        load(path)
    except DopeSlamError as e:
        assert str(e).startswith(str(path)) and "\n" not in str(e).strip(), str(e)


def test_the_property_suites_can_fail():
    with pytest.raises(ScenarioError):
        with_overrides(BASE, light=2.0)
