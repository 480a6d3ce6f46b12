"""Study (issue #26): how well the floor's region measures a step at ground truth's poses and at a run's estimate.

    python scripts/road_region_pose_study.py SEQUENCE RUN_DIR [--set K=V ...]

``SEQUENCE``: a rendered sequence (``camera.yaml``, ``images/``, ``groundtruth.txt``, e.g. a scale suite render);
``RUN_DIR``: a run of it (``stats.csv``, ``trajectory_online.txt``, ``trajectory.txt``). Each keyframe step of the run
is measured as the back end's cue measures it (``RoadRegionCue``: the pooled pitch, the defaults of
``backend.ground.road_region`` with ``--set KEY=VALUE``, a key of that section) at the poses of

* ground truth,
* the run's online estimate (the poses the back end measured the step at, near enough),
* the estimate with its rotation from ground truth, and with its direction from ground truth,

and the measured camera distance is printed against ground truth's: median, standard deviation, interquartile half
width. With ``tilt_ridge_deg`` the estimate's step is also taken along its ridge with the camera's tilt
(``ridge_factor``) at the final trajectory's tilt and at ground truth's (the steps whose ridge was measured: they
may be fewer than the estimate's). Read-only; the numbers of
docs/scale_suite.md ("The region's step rides on the estimate's tilt") came from it.
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import cv2
import gtsam
import numpy as np
from pydantic import ValidationError

from windowvo.backend.road_region import RoadRegionCue
from windowvo.config import RoadRegionConfig
from windowvo.errors import WindowVOError
from windowvo.io.sequence import read_camera_yaml
from windowvo.io.trajectory import read_tum

MODES = ("ground truth", "estimate", "estimate, rotation from truth", "estimate, direction from truth")


def poses_by_time(path: Path) -> dict[float, np.ndarray]:
    """A TUM trajectory's poses (``io.trajectory.read_tum``) by time, rounded to 0.1 ms (as ``stats.csv`` gives it)."""
    traj = read_tum(path)
    return {round(float(t), 4): T for t, T in zip(traj.timestamps, traj.T_world_base)}


def step_in(mode: str, D_truth: np.ndarray, D_est: np.ndarray) -> np.ndarray:
    """Camera k in camera k-1 as ``mode`` takes it."""
    if mode == MODES[0]:
        return D_truth
    D = D_est.copy()
    if mode == MODES[2]:
        D[:3, :3] = D_truth[:3, :3]
    elif mode == MODES[3]:
        D[:3, 3] = D_truth[:3, 3] / np.linalg.norm(D_truth[:3, 3]) * np.linalg.norm(D_est[:3, 3])
    return D


def tilt(D: np.ndarray, R_measured: np.ndarray) -> float:
    """Camera k's tilt about its x axis in ``D`` against the rotation a step was measured at (``_ridge_error``)."""
    return float(gtsam.Rot3.Logmap(gtsam.Rot3(D[:3, :3].T @ R_measured))[0])


def summary(name: str, ratios: list[float]) -> str:
    r = np.asarray(ratios) - 1.0
    if len(r) == 0:
        return f"| {name} | 0 | | | |"
    q1, q3 = np.percentile(r, [25, 75])
    return (f"| {name} | {len(r)} | {100 * np.median(r):+.2f}% | {100 * r.std():.2f}% | "
            f"{50 * (q3 - q1):.2f}% |")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequence", type=Path)
    ap.add_argument("run", type=Path)
    ap.add_argument("--set", action="append", default=[], metavar="K=V", help="a road_region key (repeatable)")
    args = ap.parse_args(argv)
    try:
        cam = read_camera_yaml(args.sequence / "camera.yaml")
        bad = [kv for kv in args.set if "=" not in kv]
        if bad:
            raise ValueError(f"--set takes KEY=VALUE, got {bad[0]!r}")
        over = dict(kv.split("=", 1) for kv in args.set)
        try:
            cfg = RoadRegionConfig.model_validate({"enabled": True, **over})
        except ValidationError as err:
            e = err.errors()[0]
            raise ValueError(f"--set {'.'.join(map(str, e['loc']))}: {e['msg']}") from None
        truth = poses_by_time(args.sequence / "groundtruth.txt")
        online = poses_by_time(args.run / "trajectory_online.txt")
        final = poses_by_time(args.run / "trajectory.txt")
        with open(args.run / "stats.csv", newline="") as f:
            rows = [r for r in csv.DictReader(f) if r["is_keyframe"] in ("True", "true", "1")]
        images = sorted((args.sequence / "images").iterdir())
    except (OSError, ValueError, WindowVOError) as err:
        print(f"road_region_pose_study.py: error: {err}", file=sys.stderr)
        return 2
    T_bc = cam.T_base_cam
    cues = {m: RoadRegionCue(cam, cfg, T_bc) for m in MODES}
    ratios: dict[str, list[float]] = {m: [] for m in (*MODES, "ridge at the final tilt", "ridge at truth's tilt")}
    prev = None
    for j, row in enumerate(rows):
        t = round(float(row["timestamp"]), 4)
        image = cv2.imread(str(images[int(row["frame_index"])]), cv2.IMREAD_GRAYSCALE)
        for cue in cues.values():
            cue.keep_image(j, image)
        if prev is not None and all(t in d and prev in d for d in (truth, online, final)):
            C0 = truth[prev] @ T_bc
            D_truth = np.linalg.inv(C0) @ truth[t] @ T_bc
            D_est = np.linalg.inv(online[prev] @ T_bc) @ online[t] @ T_bc
            D_final = np.linalg.inv(final[prev] @ T_bc) @ final[t] @ T_bc
            d = float(np.linalg.norm(D_truth[:3, 3]))
            for m, cue in cues.items():
                D = step_in(m, D_truth, D_est)
                st = cue.measure(j, truth[prev], C0 @ D @ np.linalg.inv(T_bc), np.array([0.0, 0.0, 1.0]), 0.0,
                                 ridge=cfg.tilt_ridge_deg > 0)
                if st is None:
                    continue
                ratios[m].append(st.camera_m / d)
                if m == MODES[1] and st.tilt_slope != 0.0 and st.R_cam0_cam1 is not None:
                    for name, D_at in (("ridge at the final tilt", D_final), ("ridge at truth's tilt", D_truth)):
                        ratios[name].append(st.camera_m * np.exp(st.tilt_slope * tilt(D_at, st.R_cam0_cam1)) / d)
        for cue in cues.values():
            cue.forget_before(j - 1)
        prev = t
    print(f"{args.sequence.name}: the region's camera distance against ground truth's, per keyframe step\n")
    print("| poses | steps | median | std | IQR / 2 |\n|---|---|---|---|---|")
    for name, r in ratios.items():
        if r or name in MODES:
            print(summary(name, r))
    return 0


if __name__ == "__main__":
    sys.exit(main())
