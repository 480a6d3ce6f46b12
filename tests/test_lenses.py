"""Real lenses end to end: rendered radtan and fisheye sequences through the whole pipeline, and the
synth command line's lens options."""

import subprocess
import sys

import numpy as np
import pytest
from conftest import make_config

from windowvo.camera import DistortionModel
from windowvo.io.sequence import load_native
from windowvo.runtime.job import run_job
from windowvo.synth.generate import LENSES, LensPreset, lens_fields
from windowvo.synth.paths import PathKind

# Short (20 s, 16 m) sequences; the bounds are those of the pinhole regression runs (test_pipeline.py).
CASES = {
    "radtan_loop": dict(path=PathKind.LOOP, duration_s=20.0, seed=24, **lens_fields(LensPreset.RADTAN)),
    "fisheye_figure_eight_vibration": dict(path=PathKind.FIGURE_EIGHT, duration_s=20.0, seed=25, vibration_deg=1.5,
                                           **lens_fields(LensPreset.FISHEYE)),
}


@pytest.mark.slow
@pytest.mark.parametrize("name", list(CASES))
def test_vo_with_real_lenses_beats_wheel_odometry(seq_factory, tmp_path, name):
    seq = seq_factory(name, **CASES[name])
    rep = run_job(make_config(seq, tmp_path / "out"))
    cam = rep.sequence.camera
    assert cam.distortion_model is CASES[name]["distortion_model"] and cam.has_distortion
    if cam.distortion_model is DistortionModel.EQUIDISTANT:  # wider than a hemisphere in the corners
        corners = np.array([[0.0, 0.0], [cam.width - 1.0, cam.height - 1.0]])
        assert np.degrees(cam.ray_angle(corners)).min() > 90.0
    r = rep.result
    assert len(r.trajectory) == len(rep.sequence)
    assert rep.accuracy.path_length_m > 15.0
    assert r.n_resets == 0
    # metric: ATE after SE(3) alignment at most a third of the wheel-only ATE
    assert rep.accuracy.ate_se3_rmse_m <= rep.wheel_accuracy.ate_se3_rmse_m / 3.0, (rep.accuracy, rep.wheel_accuracy)
    assert rep.accuracy.ate_se3_rmse_m < 0.1


def _synth(tmp_path, *args):
    return subprocess.run([sys.executable, "-m", "windowvo.synth", str(tmp_path / "seq"), "--duration", "0.2",
                           "--obstacles", "0", *args], capture_output=True, text=True, timeout=300)


def test_synth_lens_presets_and_overrides(tmp_path):
    r = _synth(tmp_path, "--lens", "fisheye")
    assert r.returncode == 0, r.stderr
    seq = load_native(tmp_path / "seq")
    lens = LENSES[LensPreset.FISHEYE]
    assert seq.camera.distortion_model is DistortionModel.EQUIDISTANT
    assert seq.camera.fx == lens.fx and seq.camera.distortion == lens.distortion
    assert len(seq) == 5
    r = _synth(tmp_path, "--lens", "radtan", "--fx", "300", "--distortion=-0.2,0.05,0,0")
    assert r.returncode == 0, r.stderr
    cam = load_native(tmp_path / "seq").camera
    assert (cam.distortion_model, cam.fx, cam.distortion) == (DistortionModel.RADTAN, 300.0, (-0.2, 0.05, 0.0, 0.0))


def test_synth_bad_lens_is_one_line(tmp_path):
    r = _synth(tmp_path, "--lens", "radtan", "--distortion", "0.1")
    assert r.returncode == 2
    assert r.stderr.startswith("windowvo: error:") and "radtan" in r.stderr and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "seq").exists()  # nothing written
