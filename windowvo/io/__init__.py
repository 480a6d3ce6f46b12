"""Input and output: one loader per dataset layout behind :func:`load`, sequences, trajectories, wheel odometry.

``load(cfg)`` picks the loader registered for ``cfg.dataset`` (``LOADERS``): each loader module
(``native``/``sequence``, ``kitti``, ``tum``, ``euroc``, ``folder``, ``rosbag``, ``video``) has a
``load(cfg) -> Sequence``; what every loader shares is in ``common``. Then the config-level options
common to every layout (synthetic wheel odometry) are applied.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # pragma: no cover
    from ..config import Config, DatasetKind
    from .sequence import Sequence


def _native(cfg: Config) -> Sequence:
    from .sequence import load_native

    return load_native(cfg.sequence, cfg.fps)


def _kitti(cfg: Config) -> Sequence:
    from . import kitti

    return kitti.load(cfg)


def _tum(cfg: Config) -> Sequence:
    from . import tum

    return tum.load(cfg)


def _euroc(cfg: Config) -> Sequence:
    from . import euroc

    return euroc.load(cfg)


def _folder(cfg: Config) -> Sequence:
    from . import folder

    return folder.load(cfg)


def _rosbag(cfg: Config) -> Sequence:
    from . import rosbag  # imported on demand: the rosbags library is only needed for bags

    return rosbag.load(cfg)


def _video(cfg: Config) -> Sequence:
    from . import video

    return video.load(cfg)


def loaders() -> dict[DatasetKind, Callable[[Config], Sequence]]:
    """The dataset registry: one loader per ``dataset:`` kind (modules imported when used)."""
    from ..config import DatasetKind

    return {DatasetKind.NATIVE: _native, DatasetKind.KITTI: _kitti, DatasetKind.TUM: _tum,
            DatasetKind.EUROC: _euroc, DatasetKind.FOLDER: _folder, DatasetKind.ROSBAG: _rosbag,
            DatasetKind.VIDEO: _video}


def load(cfg: Config) -> Sequence:
    """Load the configured sequence with its layout's loader, then apply the options common to every
    layout (wheel odometry synthesised from ground truth when ``odometry_synthesis`` asks for it)."""
    return finish_sequence(loaders()[cfg.dataset](cfg), cfg)


def finish_sequence(seq: Sequence, cfg: Config) -> Sequence:
    """Apply the config-level options common to every loader (synthetic wheel odometry)."""
    from ..errors import SequenceError
    from .odometry_synthesis import synthesize_odometry
    from .sequence import require_two_frames

    require_two_frames(len(seq), seq.root)

    osyn = cfg.odometry_synthesis
    if osyn.enabled and seq.odometry is None:
        if seq.groundtruth is None:
            raise SequenceError("odometry_synthesis needs ground truth, and this sequence has none")
        seq.odometry = synthesize_odometry(seq.groundtruth, osyn.scale_error, osyn.yaw_bias_per_m, osyn.noise,
                                           osyn.seed, "synthetic")
        seq.warnings.append("wheel odometry is SYNTHETIC (made from ground truth with errors)")
    return seq
