"""The shared renders of tests/conftest.py: a sequence made from another spec's render is the sequence
generate_sequence writes for its own spec, file for file (pixels, tables)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from windowvo.synth.generate import SynthSpec, WheelErrorModel, generate_sequence, pixels_spec
from windowvo.synth.paths import PathKind

SMALL = dict(path=PathKind.LOOP, duration_s=1.0, seed=3, width=160, height=120, fx=85.0)
TABLES = ("times.txt", "camera.yaml", "odometry.csv", "groundtruth.txt")
CASES = {
    "told_otherwise": dict(wheel=WheelErrorModel(scale_error=-0.04, slip_windows=[(0.2, 0.5, 0.4)]),
                           calib_pitch_error_deg=1.0),
    "frame_faults": dict(floor_hidden_frames=6, black_frames=[3, 12], duplicate_frames=[8, 9], dropped_frames=[4, 5],
                         corrupt_frames=[15], wheel=WheelErrorModel(scale_error=0.03)),
    "duplicate_after_edit": dict(floor_hidden_frames=3, duplicate_frames=[0, 2, 3], black_frames=[1]),
}


def _same_sequence(a, b) -> None:
    for name in TABLES:
        assert (a / name).read_text() == (b / name).read_text(), name
    imgs_a, imgs_b = sorted((a / "images").iterdir()), sorted((b / "images").iterdir())
    assert [p.name for p in imgs_a] == [p.name for p in imgs_b]
    for pa, pb in zip(imgs_a, imgs_b):
        ia, ib = cv2.imread(str(pa), cv2.IMREAD_UNCHANGED), cv2.imread(str(pb), cv2.IMREAD_UNCHANGED)
        if ib is None:  # a corrupt frame: the same bytes
            assert ia is None and pa.read_bytes() == pb.read_bytes(), pa.name
        else:
            assert ia is not None and ia.dtype == ib.dtype and np.array_equal(ia, ib), pa.name


@pytest.mark.parametrize("case", list(CASES))
def test_a_sequence_from_a_shared_render_is_its_own_render(seq_factory, tmp_path, case):
    spec = SynthSpec(**SMALL, **CASES[case])
    shared = seq_factory(f"shared_{case}", **SMALL, **CASES[case])
    assert pixels_spec(spec) == SynthSpec(**SMALL)  # made from the plain render, not rendered again
    generate_sequence(tmp_path / "direct", spec)
    _same_sequence(shared, tmp_path / "direct")


def test_image_noise_is_rendered_again(seq_factory):
    """Image noise draws from one random stream frame after frame, so a spec with faults is rendered as is."""
    spec = SynthSpec(**SMALL, image_noise=1.0, dropped_frames=[2])
    assert pixels_spec(spec) == spec


def test_images_from_refuses_a_noisy_spec(tmp_path):
    with pytest.raises(ValueError, match="image noise"):
        generate_sequence(tmp_path / "x", SynthSpec(**SMALL, image_noise=1.0), images_from=tmp_path)
