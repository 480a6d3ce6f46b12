"""A new user's first day (issue #28): convert, the streaming API's loaders, the config's YAML, the
default mounting's warning, hints for another layout, plain --help texts, example.yaml, scale sources."""

from __future__ import annotations

import enum
import logging
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from windowvo import io
from windowvo.camera import CameraModel, DistortionModel
from windowvo.config import (
    Config,
    ConfigError,
    DatasetKind,
    MountCalibration,
    OdometrySourceKind,
    RerunMode,
    RobustKind,
    RunMode,
    TrackerKind,
    config_from_dict,
    load_config,
    load_robot_config,
)
from windowvo.errors import SequenceError, WindowVOError
from windowvo.io.common import DEFAULT_MOUNTING_WARNING, T_BASE_CAM_FORWARD
from windowvo.io.sequence import load_native, read_camera_yaml, write_camera_yaml
from windowvo.tools import convert as convert_tool

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
KITTI06 = SHARED_DATA / "kitti06_000-050"
EXAMPLE = Path(__file__).resolve().parents[1] / "configs" / "example.yaml"
ROOT = Path(__file__).resolve().parents[1]


def _camera(z: float = 0.3, numpy_numbers: bool = False) -> CameraModel:
    T = T_BASE_CAM_FORWARD.copy()
    T[2, 3] = z
    f = np.float64 if numpy_numbers else float
    return CameraModel(64, 48, f(50.5), f(50.5), f(32.0), f(24.0), DistortionModel.NONE, (), T)


def _images(folder: Path, n: int = 4) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    for i in range(n):
        cv2.imwrite(str(folder / f"{i:06d}.png"), rng.integers(0, 255, (48, 64), dtype=np.uint8))


def _run(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, timeout=300, cwd=cwd)


# ---------------------------------------------------------------------------- 1. convert


def test_camera_yaml_with_numpy_numbers_round_trips(tmp_path):
    cam = _camera(numpy_numbers=True)
    write_camera_yaml(tmp_path / "camera.yaml", cam)
    text = (tmp_path / "camera.yaml").read_text()
    assert "numpy" not in text and "!!" not in text
    back = read_camera_yaml(tmp_path / "camera.yaml")
    assert back.fx == 50.5 and type(back.fx) is float and np.array_equal(back.T_base_cam, cam.T_base_cam)


@pytest.mark.skipif(not KITTI06.is_dir(), reason="KITTI excerpt not in ../shared/data")
def test_convert_kitti_from_the_command_line(tmp_path):
    (tmp_path / "kitti06.yaml").write_text(f"sequence: {KITTI06}\ndataset: kitti\n")
    proc = _run("-m", "windowvo.convert", "kitti06.yaml", "OUT", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    out = tmp_path / "OUT"
    seq = load_native(out)
    assert len(seq) == len(list((KITTI06 / "image_0").iterdir()))
    assert seq.camera.fx == pytest.approx(707.0912) and seq.groundtruth is not None
    assert sorted(p.name for p in tmp_path.iterdir()) == ["OUT", "kitti06.yaml"]  # no partial folder left


def test_a_failed_convert_leaves_nothing(tmp_path, monkeypatch):
    root = tmp_path / "plain"
    _images(root)
    cfg = config_from_dict({"sequence": str(root), "output": str(tmp_path / "o"), "dataset": "folder",
                            "camera": {"width": 64, "height": 48, "fx": 50, "fy": 50, "cx": 32, "cy": 24}})
    seq = io.load(cfg)

    def broken(path, cam):
        raise WindowVOError("disk full")

    monkeypatch.setattr(convert_tool, "write_camera_yaml", broken)
    out = tmp_path / "conv" / "native"
    with pytest.raises(WindowVOError, match="disk full"):
        convert_tool.convert(seq, out)
    assert list((tmp_path / "conv").iterdir()) == []  # neither OUT nor the temporary folder
    monkeypatch.undo()
    convert_tool.convert(seq, str(out))  # a str works too
    assert len(load_native(out)) == 4
    with pytest.raises(WindowVOError, match="not an empty folder"):
        convert_tool.convert(seq, out)


# ---------------------------------------------------------------------------- 2. streaming API, robot config


def test_read_camera_yaml_and_load_config_take_str(tmp_path):
    write_camera_yaml(tmp_path / "camera.yaml", _camera())
    assert read_camera_yaml(str(tmp_path / "camera.yaml")).width == 64
    (tmp_path / "run.yaml").write_text("sequence: s\noutput: o\n")
    assert load_config(str(tmp_path / "run.yaml")).sequence == (tmp_path / "s").resolve()


def test_robot_config_needs_no_sequence_or_output(tmp_path):
    (tmp_path / "robot.yaml").write_text("frontend:\n  max_features: 150\n  mask: body.png\n")
    cfg = load_robot_config(str(tmp_path / "robot.yaml"))
    assert cfg.frontend.max_features == 150
    assert cfg.frontend.mask == (tmp_path / "body.png").resolve()  # relative to the file
    with pytest.raises(ConfigError, match="'sequence': required key is missing"):
        load_config(tmp_path / "robot.yaml")  # a file run still needs them
    with pytest.raises(ConfigError, match=r"frontend\.max_features"):
        load_robot_config(tmp_path / "robot.yaml", ["frontend.max_features=3"])


def test_odometry_from_a_robot_config_file(tmp_path):
    import windowvo

    (tmp_path / "robot.yaml").write_text("frontend:\n  max_features: 150\nbackend:\n  use_odometry: false\n")
    vo = windowvo.Odometry.from_config(str(tmp_path / "robot.yaml"), _camera())
    assert vo.cfg.frontend.max_features == 150 and not vo.use_odometry
    assert windowvo.Odometry.from_config(tmp_path / "robot.yaml", _camera()).cfg.frontend.max_features == 150


def test_config_errors_name_every_problem():
    with pytest.raises(ConfigError) as err:
        config_from_dict({"frontend": {"max_features": "many", "bogus": 1}})
    msg = str(err.value)
    for part in ("'sequence': required key is missing", "'output': required key is missing",
                 "'frontend.max_features'", "'frontend.bogus': unknown key"):
        assert part in msg
    assert "more problem" not in msg and "\n" not in msg


# ---------------------------------------------------------------------------- 3. floats in the config


def test_config_reads_every_float_spelling(tmp_path):
    (tmp_path / "c.yaml").write_text("sequence: s\noutput: o\nfps: 3.4e1\nfrontend:\n  quality_level: 1e-2\n")
    cfg = load_config(tmp_path / "c.yaml", ["keyframes.min_parallax_px=2.5E+1"])
    assert cfg.fps == 34.0 and cfg.frontend.quality_level == 0.01 and cfg.keyframes.min_parallax_px == 25.0


# ---------------------------------------------------------------------------- 4. the default mounting


@pytest.mark.parametrize("with_mount", [False, True])
def test_default_mounting_is_said_once_at_load(tmp_path, caplog, with_mount):
    _images(tmp_path / "plain")
    camera: dict = {"width": 64, "height": 48, "fx": 50, "fy": 50, "cx": 32, "cy": 24}
    if with_mount:
        camera["T_base_cam"] = [float(x) for x in _camera().T_base_cam.ravel()]
    cfg = config_from_dict({"sequence": str(tmp_path / "plain"), "output": str(tmp_path / "o"),
                            "dataset": "folder", "camera": camera})
    with caplog.at_level(logging.WARNING):
        seq = io.load(cfg)
    # once: in the sequence's warnings, which the job prints at the start of a run (not logged twice)
    said = [w for w in seq.warnings if w == DEFAULT_MOUNTING_WARNING]
    said += [r for r in caplog.records if r.getMessage() == DEFAULT_MOUNTING_WARNING]
    assert len(said) == (0 if with_mount else 1)
    assert seq.camera.T_base_cam[2, 3] == (0.3 if with_mount else 0.0)
    assert "height 0" in DEFAULT_MOUNTING_WARNING and "set camera.T_base_cam" in DEFAULT_MOUNTING_WARNING


# ---------------------------------------------------------------------------- 5. another layout's folder


def _make_layout(root: Path, kind: DatasetKind) -> Path:
    root.mkdir()
    if kind is DatasetKind.KITTI:
        (root / "image_0").mkdir()
        (root / "calib.txt").write_text("P0: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    elif kind is DatasetKind.TUM:
        (root / "rgb.txt").write_text("# timestamp filename\n")
    elif kind is DatasetKind.EUROC:
        (root / "mav0").mkdir()
    elif kind is DatasetKind.ROSBAG:
        (root / "run.mcap").write_bytes(b"")
    elif kind is DatasetKind.VIDEO:
        (root / "drive.mp4").write_bytes(b"")
        return root / "drive.mp4"
    return root


@pytest.mark.parametrize("kind", [DatasetKind.KITTI, DatasetKind.TUM, DatasetKind.EUROC, DatasetKind.ROSBAG,
                                  DatasetKind.VIDEO])
def test_native_config_on_another_layout_says_which(tmp_path, kind):
    target = _make_layout(tmp_path / "data", kind)
    cfg = config_from_dict({"sequence": str(target), "output": str(tmp_path / "o")})
    with pytest.raises(SequenceError) as err:
        io.load(cfg)
    assert f"set dataset: {kind.value}" in str(err.value)
    if kind is DatasetKind.KITTI:
        assert str(err.value).endswith("looks like a KITTI folder: set dataset: kitti")


def test_native_folder_without_images_and_no_other_layout_gets_no_hint(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(SequenceError) as err:
        load_native(tmp_path / "empty")
    assert str(err.value) == f"image folder not found: {tmp_path / 'empty' / 'images'}"


# ---------------------------------------------------------------------------- 6. --help, example.yaml

OTHER_OWNERS: dict[str, str] = {}


@pytest.mark.parametrize("module", ["run", "batch", "bench", "convert", "topics", "config_doc", "eval", "synth",
                                    "synth.bagwriter", "view"])
def test_help_has_no_markup(module):
    if module in OTHER_OWNERS:
        pytest.xfail(f"{OTHER_OWNERS[module]} formats its docstring as is (windowvo.tools.helptext.plain_help)")
    proc = _run("-m", f"windowvo.{module}", "--help", cwd=ROOT)
    assert proc.returncode == 0, proc.stderr
    assert "`" not in proc.stdout, proc.stdout
    assert "usage: python -m windowvo." in proc.stdout


def _enum_values(*kinds: type[enum.Enum]) -> set[str]:
    return {str(v.value) for k in kinds for v in k}


def test_example_config_shows_every_section_and_option():
    text = EXAMPLE.read_text()
    keys_shown = {line.lstrip("# ").split(":")[0] for line in text.splitlines() if ":" in line}
    for name in Config.model_fields:
        assert name in keys_shown, f"example.yaml does not show '{name}'"
    words = set(text.replace("|", " ").replace(",", " ").replace("(", " ").replace(")", " ").split())
    values = _enum_values(RobustKind, DatasetKind, TrackerKind, RunMode, RerunMode, MountCalibration,
                          OdometrySourceKind, DistortionModel)
    assert values <= words, f"example.yaml does not name {sorted(values - words)}"
    # Every section that is not commented out is a section of the config (and loads).
    assert set(yaml.safe_load(text)) <= set(Config.model_fields)


# ---------------------------------------------------------------------------- 7. scale sources


@pytest.mark.parametrize("late_start", [False, True])
def test_a_monocular_run_made_metric_by_the_floor_names_it(late_start):
    from windowvo.backend.report import scale_report
    from windowvo.backend.smoother import SlidingWindowBackend
    from windowvo.config import BackendConfig
    from windowvo.types import ScaleSource

    be = SlidingWindowBackend(_camera(z=1.65), BackendConfig(), use_odometry=False)
    assert be.use_ground and be.scale_sources() == []  # not metric yet: nothing fixes the scale
    # Metric by the floor (the first baseline, or a late metric start), before any ground factor went in.
    be.floor.metric = True
    if late_start:
        be.floor.metric_from_keyframe = 0
        be.kf_frame[0] = 108
    assert be.floor.n_ground_factors == 0
    assert be.scale_sources() == [ScaleSource.GROUND_PLANE]
    report = scale_report(be)
    assert report.metric and report.scale_sources == [ScaleSource.GROUND_PLANE.value]
    assert report.metric_from_frame == (108 if late_start else None)
