from pathlib import Path

import pytest

from windowvo.config import RerunMode, TrackerKind, load_config
from windowvo.errors import ConfigError


def write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "cfg.yaml"
    p.write_text(text)
    return p


def test_minimal_config_and_relative_paths(tmp_path):
    cfg = load_config(write(tmp_path, "sequence: seq\noutput: out\n"))
    assert cfg.sequence == (tmp_path / "seq").resolve()
    assert cfg.output == (tmp_path / "out").resolve()
    assert cfg.frontend.max_features == 200
    assert cfg.viz.rerun is RerunMode.SAVE


def test_overrides_are_typed(tmp_path):
    cfg = load_config(write(tmp_path, "sequence: s\noutput: o\n"),
                      ["frontend.max_features=300", "frontend.tracker=orb", "viz.rerun=off", "backend.planar_prior.enabled=false"])
    assert cfg.frontend.max_features == 300
    assert cfg.frontend.tracker is TrackerKind.ORB
    assert cfg.viz.rerun is RerunMode.OFF
    assert cfg.backend.planar_prior.enabled is False


@pytest.mark.parametrize(
    "text,needle",
    [
        ("sequence: s\noutput: o\nfrontend:\n  max_feature: 3\n", "'frontend.max_feature': unknown key"),
        ("sequence: s\noutput: o\nfrontend:\n  max_features: lots\n", "'frontend.max_features'"),
        ("sequence: s\noutput: o\nbackend:\n  window_keyframes: 0\n", "'backend.window_keyframes'"),
        ("sequence: s\noutput: o\nbackend:\n  pixel_sigma: -1\n", "'backend.pixel_sigma'"),
        ("output: o\n", "'sequence': required key is missing"),
        ("sequence: s\noutput: o\ndataset: rosbag\n", "'dataset'"),
        ("- a\n- b\n", "mapping"),
        ("sequence: [unclosed\n", "not valid YAML"),
    ],
)
def test_bad_config_gives_one_clear_line(tmp_path, text, needle):
    with pytest.raises(ConfigError) as exc:
        load_config(write(tmp_path, text))
    msg = str(exc.value)
    assert needle in msg
    assert "\n" not in msg


def test_bad_override(tmp_path):
    with pytest.raises(ConfigError, match="key=value"):
        load_config(write(tmp_path, "sequence: s\noutput: o\n"), ["frontend.max_features"])
    with pytest.raises(ConfigError, match="unknown key"):
        load_config(write(tmp_path, "sequence: s\noutput: o\n"), ["frontend.nope=1"])


def test_missing_config_file(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "nope.yaml")


def test_example_config_is_valid():
    cfg = load_config(Path(__file__).resolve().parents[1] / "configs" / "example.yaml")
    assert cfg.frontend.tracker is TrackerKind.KLT and cfg.backend.window_keyframes == 20
