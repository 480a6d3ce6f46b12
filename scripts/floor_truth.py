"""Where a run's floor points really are, on a rendered sequence (a study tool, docs/scale_suite.md).

    python scripts/floor_truth.py CONFIG.yaml [dotted.key=value ...]

Runs the config (sequentially, in this process) and, for every landmark the back end tied to the floor and every
floor candidate it judged (below the horizon, in range, at a keyframe with a fitted plane), triangulates the
track's observations with the ground-truth camera poses (``groundtruth.txt``; the rendered floor is z = 0): its
true height above the floor, free of the run's own pose and scale errors. Prints the heights' percentiles for
the tied points and the candidates' medians, selected and rejected. Hooks the back end's classes for the run
(``FloorModel.floor_of``, ``FloorModel.birth_ground_factor``, ``LandmarkManager.promote``); nothing is written.
"""

from __future__ import annotations

import sys

import gtsam
import numpy as np

from windowvo.backend import floor as floor_model
from windowvo.backend import landmarks, smoother
from windowvo.backend.ground import floor_candidates
from windowvo.config import load_config
from windowvo.errors import WindowVOError
from windowvo.runtime.job import run_job

BACKENDS: list = []
BORN_OBS: dict[int, list[tuple[int, np.ndarray]]] = {}  # floor landmark -> its observations when it was born
CANDIDATES: list[tuple[bool, list[tuple[int, np.ndarray]]]] = []  # (selected, observations) of floor candidates


def _hook() -> None:
    init, promote, floor_of = (smoother.SlidingWindowBackend.__init__, landmarks.LandmarkManager.promote,
                               floor_model.FloorModel.floor_of)

    def init_hook(self, *a, **kw):
        init(self, *a, **kw)
        BACKENDS.append(self)

    def promote_hook(self, tid, k, on_ground):
        obs = promote(self, tid, k, on_ground)
        if on_ground:
            BORN_OBS[tid] = [(kk, np.asarray(uv, float)) for kk, uv, _ in obs]
        return obs

    def floor_of_hook(self, k, born, T_guess):
        mask, fit = floor_of(self, k, born, T_guess)
        if born and fit is not None:
            p_base = (np.asarray([p for _, p in born]) - T_guess[:3, 3]) @ T_guess[:3, :3]
            cand = floor_candidates(p_base, self.T_base_cam[:3, 3], self.camera_height_m, self.cfg.ground)
            for (tid, _), m, c in zip(born, mask, cand):
                if c:
                    CANDIDATES.append((bool(m), [(kk, np.asarray(uv, float)) for kk, uv, _ in self.lm.obs.get(tid, [])]))
        return mask, fit

    smoother.SlidingWindowBackend.__init__ = init_hook  # type: ignore[method-assign]
    landmarks.LandmarkManager.promote = promote_hook  # type: ignore[method-assign]
    floor_model.FloorModel.floor_of = floor_of_hook  # type: ignore[method-assign]


def _groundtruth(folder: str) -> list[np.ndarray]:
    poses = []
    with open(f"{folder}/groundtruth.txt") as f:
        lines = f.readlines()
    for line in lines:
        if line.startswith("#") or not line.strip():
            continue
        _, x, y, z, qx, qy, qz, qw = map(float, line.split())
        T = np.eye(4)
        T[:3, :3] = gtsam.Rot3.Quaternion(qw, qx, qy, qz).matrix()
        T[:3, 3] = (x, y, z)
        poses.append(T)
    return poses


def _true_height(obs, be, gt) -> float | None:
    """Least-squares intersection of the observations' rays from the ground-truth cameras: its z."""
    Kinv = np.linalg.inv(be.K.K())
    A, b = [], []
    for kk, uv in obs:
        f = be.kf_frame.get(kk)
        if f is None or f >= len(gt):
            continue
        T_world_cam = gt[f] @ be.T_base_cam
        d = T_world_cam[:3, :3] @ (Kinv @ np.array([uv[0], uv[1], 1.0]))
        d /= np.linalg.norm(d)
        P = np.eye(3) - np.outer(d, d)
        A.append(P)
        b.append(P @ T_world_cam[:3, 3])
    if len(A) < 2:
        return None
    return float(np.linalg.lstsq(np.concatenate(A), np.concatenate(b), rcond=None)[0][2])


def main(argv: list[str]) -> int:
    _hook()
    cfg = load_config(argv[0], argv[1:])
    rep = run_job(cfg)
    be, gt = BACKENDS[-1], _groundtruth(str(cfg.sequence))
    h = be.floor.camera_height_m
    tied = np.array([z for z in (_true_height(o, be, gt) for o in BORN_OBS.values()) if z is not None])
    print(f"{len(tied)} tied floor landmarks; camera height {h:.3f} m; ATE SE(3) "
          f"{rep.accuracy.ate_se3_rmse_m if rep.accuracy else float('nan'):.4f} m")
    print("true height above the floor, m (5/25/50/75/95%):", np.percentile(tied, [5, 25, 50, 75, 95]).round(4))
    sel = [z for m, o in CANDIDATES if m and (z := _true_height(o, be, gt)) is not None and abs(z) < 0.5 * h]
    rej = [z for m, o in CANDIDATES if not m and (z := _true_height(o, be, gt)) is not None and abs(z) < 0.5 * h]
    if sel and rej:
        print(f"floor candidates (true height within half the camera height): median {np.median(sel + rej):.4f} m, "
              f"selected {len(sel)} {np.median(sel):.4f} m, rejected {len(rej)} {np.median(rej):.4f} m")
    return 0


if __name__ == "__main__":
    if len(sys.argv) < 2:
        print("usage: python scripts/floor_truth.py CONFIG.yaml [dotted.key=value ...]", file=sys.stderr)
        sys.exit(2)
    try:
        sys.exit(main(sys.argv[1:]))
    except (WindowVOError, OSError) as err:  # a bad config, a sequence without groundtruth.txt: one line
        print(f"floor_truth: error: {err}", file=sys.stderr)
        sys.exit(2)
