"""Property-based fuzzing of the input loaders: every invalid input is a clear windowvo error."""

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from windowvo.config import ConfigError, config_from_dict
from windowvo.errors import WindowVOError
from windowvo.io.odometry import read_odometry_csv
from windowvo.io.sequence import read_camera_yaml, read_times

FUZZ = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])

scalars = st.one_of(st.none(), st.booleans(), st.integers(-10**6, 10**6), st.floats(allow_nan=True),
                    st.text(max_size=12))
values = st.recursive(scalars, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                       st.dictionaries(st.text(max_size=8), inner, max_size=4)),
                      max_leaves=10)
CONFIG_KEYS = ["sequence", "output", "dataset", "fps", "max_frames", "frontend", "keyframes", "gates", "backend",
               "viz", "checks", "camera", "odometry_synthesis", "progress"]
SECTION_KEYS = ["max_features", "tracker", "window_keyframes", "pixel_sigma", "robust", "rerun", "enabled",
                "min_parallax_px", "huber_k", "odometry", "planar_prior", "fx", "width"]


@FUZZ
@given(st.dictionaries(st.sampled_from([*CONFIG_KEYS, "bogus"]),
                       st.one_of(values, st.dictionaries(st.sampled_from(SECTION_KEYS), values, max_size=4)),
                       max_size=6))
def test_config_fuzz(data):
    try:
        cfg = config_from_dict(data)
    except ConfigError as err:
        assert str(err).startswith("invalid config") and "\n" not in str(err)
    else:
        assert cfg.sequence is not None and cfg.backend.window_keyframes >= 3


camera_fields = st.fixed_dictionaries(
    {},
    optional={
        "width": values, "height": values, "fx": values, "fy": values, "cx": values, "cy": values,
        "distortion_model": st.one_of(values, st.sampled_from(["none", "radtan", "equidistant"])),
        "distortion": st.one_of(values, st.lists(st.floats(-1, 1), max_size=6)),
        "T_base_cam": st.one_of(values, st.lists(st.floats(-2, 2), min_size=16, max_size=16)),
    },
)


@FUZZ
@given(st.one_of(camera_fields, values, st.text(max_size=60)))
def test_camera_yaml_fuzz(tmp_path, content):
    p = tmp_path / "camera.yaml"
    p.write_text(content if isinstance(content, str) else yaml.safe_dump(content))
    try:
        cam = read_camera_yaml(p)
    except WindowVOError as err:
        assert "\n" not in str(err)
    else:
        assert cam.fx > 0 and cam.fy > 0 and cam.width > 0


@FUZZ
@given(st.one_of(st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=8).map(lambda v: "\n".join(map(str, v))),
                 st.text(max_size=80)),
       st.integers(0, 8))
def test_times_fuzz(tmp_path, text, n):
    p = tmp_path / "times.txt"
    p.write_text(text)
    try:
        t = read_times(p, n)
    except WindowVOError as err:
        assert "\n" not in str(err)
    else:
        assert len(t) == n and np.all(np.isfinite(t)) and np.all(np.diff(t) > 0)


rows = st.lists(st.lists(st.one_of(st.floats(allow_nan=True, allow_infinity=True).map(str), st.text(max_size=5)),
                         min_size=0, max_size=5).map(",".join), max_size=6)


@FUZZ
@given(st.sampled_from(["timestamp,x,y,yaw", "t,x,y", "", "# synthetic\ntimestamp,x,y,yaw"]), rows)
def test_odometry_csv_fuzz(tmp_path, header, body):
    p = tmp_path / "odometry.csv"
    p.write_text(header + "\n" + "\n".join(body) + "\n")
    try:
        odo = read_odometry_csv(p)
    except WindowVOError as err:
        assert "\n" not in str(err)
    else:
        assert len(odo.timestamps) >= 2 and np.all(np.diff(odo.timestamps) > 0)
        assert np.all(np.isfinite(odo.x))


def test_a_message_with_control_characters_stays_one_line():
    """A user's key or file name can hold a newline: the message shows it escaped (found by the fuzz above)."""
    from windowvo.errors import CalibrationError, ConfigError

    assert str(CalibrationError("camera.yaml: unknown key '\n'")) == "camera.yaml: unknown key '\\n'"
    assert "\n" not in str(ConfigError("a\tb\rc\x01d\ne")) and "\\x01" in str(ConfigError("\x01"))


def test_camera_yaml_keys_of_mixed_types_are_one_clear_error(tmp_path):
    """Found by the fuzz test: unknown keys of different YAML types (a string and a float) could not be sorted for
    the message (TypeError); now the one-line calibration error names one of them."""
    from windowvo.errors import CalibrationError

    p = tmp_path / "camera.yaml"
    p.write_text("'': null\n0E0: null\n")
    with pytest.raises(CalibrationError, match="unknown key"):
        read_camera_yaml(p)
