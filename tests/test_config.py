import subprocess
import sys
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
        ("sequence: s\noutput: o\ndataset: hdf5\n", "'dataset'"),
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


def _run_cli(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "windowvo.run", *args], capture_output=True, text=True, timeout=300,
                          cwd=cwd)


@pytest.mark.parametrize("where", ["output_is_file", "parent_is_file"])
def test_output_that_is_a_file_is_one_line_and_exit_2(tmp_path, where):
    """An `output:` that is an existing file (or lies under one) stops before any work, with one line."""
    blocker = tmp_path / "taken.txt"
    blocker.write_text("not a folder\n")
    out = blocker if where == "output_is_file" else blocker / "out"
    cfg = write(tmp_path, f"sequence: {tmp_path / 'seq'}\noutput: {out}\nprogress: false\nviz:\n  rerun: 'off'\n")
    r = _run_cli(str(cfg))
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("windowvo: error: output '")
    assert ("is an existing file" if where == "output_is_file" else "is a file, not a folder") in lines[0]
    assert blocker.read_text() == "not a folder\n"
