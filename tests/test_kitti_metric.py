"""The KITTI odometry metric (devkit evaluate_odometry.cpp) against hand-computed answers, and the
eval command line on TUM / KITTI files and bad input.

Fixtures are straight lines with 1 m steps along the base's x, so the ground-truth distance of
frame i is exactly i metres (float-exact). The devkit ends a segment of length L starting at frame f
at the first frame whose distance is *strictly greater* than f + L: frame f + L + 1. So every
segment really covers L + 1 metres of ground truth, and a segment exists when f + L + 1 <= N - 1.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from windowvo.errors import WindowVOError
from windowvo.eval import __main__ as eval_cli
from windowvo.eval.kitti_metric import (
    DEVKIT_STEP_FRAMES,
    SegmentSet,
    kitti_odometry_error,
    last_frame_from_segment_length,
    segment_errors,
    trajectory_distances,
)
from windowvo.geometry import make_T, rot_z, rpy_to_R
from windowvo.io.trajectory import Trajectory, write_tum

DATA = Path("/work/shared/data/kitti06_000-050")
W = make_T(rpy_to_R(0.3, -0.2, 1.1), [10.0, -4.0, 2.5])  # another world frame


def line(n: int, scale: float = 1.0, dt: float = 0.1) -> Trajectory:
    """n poses, 1 m apart (times ``scale``) along x, heading along x."""
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 3] = scale * np.arange(n, dtype=float)
    return Trajectory(dt * np.arange(n), poses)


def arc(n: int, yaw_rate_per_m: float, dt: float = 0.1) -> Trajectory:
    """What an estimate with a constant yaw-rate bias drives: 1 m of arc a frame, turning left."""
    b = yaw_rate_per_m
    s = np.arange(n, dtype=float)
    poses = np.stack([make_T(rot_z(b * si), [math.sin(b * si) / b, (1.0 - math.cos(b * si)) / b, 0.0]) for si in s])
    return Trajectory(dt * np.arange(n), poses)


def n_segments_on_line(n: int, length: float, step: int = DEVKIT_STEP_FRAMES) -> int:
    """First frames f = 0, step, ... with f + L + 1 <= n - 1."""
    return len(range(0, int(n - 1 - length - 1) + 1, step))


# ------------------------------------------------------------------------------ the rules


def test_segment_end_is_the_first_frame_strictly_past_the_length():
    """Hand-made distances: steps 4, 4, 2, 0.5, 3.5."""
    dist = trajectory_distances(np.array([[0, 0, 0], [4, 0, 0], [8, 0, 0], [8, 2, 0], [8, 2.5, 0], [8, 6, 0]], float))
    assert dist.tolist() == [0.0, 4.0, 8.0, 10.0, 10.5, 14.0]
    assert last_frame_from_segment_length(dist, 0, 10.0) == 4  # dist 10.0 is not > 10: frame 3 is not the end
    assert last_frame_from_segment_length(dist, 0, 9.5) == 3
    assert last_frame_from_segment_length(dist, 1, 6.4) == 4  # 10.5 > 4 + 6.4
    assert last_frame_from_segment_length(dist, 0, 14.0) is None  # nothing past 14 m
    assert last_frame_from_segment_length(dist, 2, 6.5) is None


def test_step_size_picks_every_tenth_first_frame():
    """25 poses, 24 m: L = 10 from f = 0 (ends at 11) and f = 10 (ends at 21), not f = 20 (needs 31);
    L = 20 only from f = 0 (ends at 21). Step 5 adds f = 5 for L = 10 (ends at 16)."""
    gt = line(25)
    lengths = SegmentSet.SHORT.lengths_m
    segs = segment_errors(gt.T_world_base, gt.T_world_base, lengths)
    assert [(s.first_frame, s.last_frame, s.length_m) for s in segs] == [(0, 11, 10.0), (0, 21, 20.0), (10, 21, 10.0)]
    segs5 = segment_errors(gt.T_world_base, gt.T_world_base, lengths, step_frames=5)
    assert [(s.first_frame, s.last_frame) for s in segs5] == [(0, 11), (0, 21), (5, 16), (10, 21)]
    rep = kitti_odometry_error(gt, gt, SegmentSet.SHORT, step_frames=5)
    assert rep.n_segments == 4 and rep.per_length[10.0].n_segments == 3 and rep.per_length[20.0].n_segments == 1
    assert set(rep.per_length) == {10.0, 20.0}


def test_segment_sets():
    assert SegmentSet.DEVKIT.lengths_m == (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)
    assert SegmentSet.SHORT.lengths_m == (10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0, 80.0)
    assert "short segments 10-80 m" in SegmentSet.SHORT.label


# ------------------------------------------------------------------------------ known answers


def expected_scale_pct(n: int, s: float, lengths: tuple[float, ...]) -> tuple[float, dict[float, float]]:
    """A line scaled by s: each segment covers L + 1 m, so its t_err is |s - 1| (L + 1) / L."""
    per = {L: 100.0 * abs(s - 1.0) * (L + 1.0) / L for L in lengths if n_segments_on_line(n, L) > 0}
    counts = {L: n_segments_on_line(n, L) for L in per}
    return sum(counts[L] * per[L] for L in per) / sum(counts.values()), per


def test_scaled_straight_line_1000m():
    """1001 poses (1000 m), the estimate 2% long (and in another world frame): t_err = 2% of the
    L + 1 m each segment covers, divided by L; no rotation error. Segments per length: 100 - L / 10."""
    n = 1001
    rep = kitti_odometry_error(line(n), transformed(line(n, 1.02), W))
    mean, per = expected_scale_pct(n, 1.02, SegmentSet.DEVKIT.lengths_m)
    assert rep.n_segments == sum(100 - int(L) // 10 for L in SegmentSet.DEVKIT.lengths_m) == 440
    assert rep.per_length[100.0].n_segments == 90 and rep.per_length[800.0].n_segments == 20
    assert rep.t_rel_pct == pytest.approx(mean, rel=1e-9)
    assert rep.per_length[100.0].t_rel_pct == pytest.approx(2.02, rel=1e-9)
    assert rep.per_length[800.0].t_rel_pct == pytest.approx(2.0025, rel=1e-9)
    for L, pct in per.items():
        assert rep.per_length[L].t_rel_pct == pytest.approx(pct, rel=1e-9)
    assert rep.r_rel_deg_per_100m == pytest.approx(0.0, abs=1e-9)
    assert rep.gt_path_length_m == pytest.approx(1000.0, rel=1e-12)
    short = kitti_odometry_error(line(n), line(n, 1.02), SegmentSet.SHORT)
    assert short.per_length[10.0].t_rel_pct == pytest.approx(2.2, rel=1e-9)  # 2% of 11 m over 10 m


def transformed(traj: Trajectory, T_left: np.ndarray) -> Trajectory:
    return Trajectory(traj.timestamps.copy(), np.einsum("ij,njk->nik", T_left, traj.T_world_base))


def test_constant_yaw_rate_bias():
    """The estimate turns 1 deg per 100 m while the truth drives straight (201 poses, 200 m).

    Over a segment of L + 1 m the error's rotation is b (L + 1): r_err = b (L + 1) / L, i.e.
    (L + 1) / L deg per 100 m. Its translation is the gap between the chord of the arc,
    (sin(b s) / b, (1 - cos(b s)) / b), and the straight (s, 0), s = L + 1."""
    b = math.radians(1.0) / 100.0
    n = 201
    gt, est = line(n), transformed(arc(n, b), W)
    for segs in SegmentSet:
        rep = kitti_odometry_error(gt, est, segs)
        assert rep.n_segments == sum(n_segments_on_line(n, L) for L in segs.lengths_m) > 0
        for L, le in rep.per_length.items():
            s = L + 1.0
            gap = math.hypot(s - math.sin(b * s) / b, (1.0 - math.cos(b * s)) / b)
            assert le.r_rel_deg_per_100m == pytest.approx((L + 1.0) / L, rel=1e-8)
            assert le.t_rel_pct == pytest.approx(100.0 * gap / L, rel=1e-6)
    dev = kitti_odometry_error(gt, est, SegmentSet.DEVKIT)
    assert set(dev.per_length) == {100.0} and dev.n_segments == 10  # f = 0..90; 200 m needs 201 m
    assert dev.r_rel_deg_per_100m == pytest.approx(1.01, rel=1e-8)
    assert dev.r_rel_deg_per_m == pytest.approx(0.0101, rel=1e-8)


def test_identical_trajectories_have_no_error():
    n = 301
    rep = kitti_odometry_error(arc(n, 0.01), transformed(arc(n, 0.01), W), SegmentSet.SHORT)
    assert rep.n_segments > 0
    assert rep.t_rel_pct == pytest.approx(0.0, abs=1e-9)
    assert rep.r_rel_deg_per_100m == pytest.approx(0.0, abs=1e-4)  # acos near 1: ~1e-8 rad of rounding


def test_too_short_gives_no_segment():
    rep = kitti_odometry_error(line(90), line(90, 1.5))  # 89 m < 100 m
    assert rep.n_segments == 0 and rep.t_rel_pct is None and rep.r_rel_deg_per_100m is None
    assert rep.per_length == {} and rep.r_rel_deg_per_m is None
    assert "n/a" in rep.summary() and "89.0 m" in rep.summary()
    assert kitti_odometry_error(line(11), line(11), SegmentSet.SHORT).n_segments == 0  # 10 m is not > 10 m
    assert json.dumps(rep.as_dict())


def test_poses_matched_by_timestamp_and_scale_applied():
    """The estimate has 20 extra poses before the truth starts and times 5 ms late: only the matched
    poses count. A monocular estimate at half scale, given its scale 2, has no error."""
    n = 101
    est = line(n + 20, 1.02)
    est.T_world_base[:, 0, 3] -= 20 * 1.02
    est = Trajectory(est.timestamps - 2.0 + 0.005, est.T_world_base)
    rep = kitti_odometry_error(line(n), est, SegmentSet.SHORT)
    mean, _ = expected_scale_pct(n, 1.02, SegmentSet.SHORT.lengths_m)
    assert rep.n_segments == sum(n_segments_on_line(n, L) for L in SegmentSet.SHORT.lengths_m)
    assert rep.t_rel_pct == pytest.approx(mean, rel=1e-9)
    half = kitti_odometry_error(line(n), line(n, 0.5), SegmentSet.SHORT, estimate_scale=2.0)
    assert half.t_rel_pct == pytest.approx(0.0, abs=1e-9) and half.estimate_scale == 2.0
    with pytest.raises(WindowVOError, match="cannot associate"):
        kitti_odometry_error(line(n), Trajectory(line(n).timestamps + 1000.0, line(n).T_world_base))


# ------------------------------------------------------------------------------ files and CLI


def write_kitti(path: Path, T_cam0_camk: np.ndarray, times: np.ndarray | None = None) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(" ".join(f"{v:.9e}" for v in T[:3, :].ravel()) + "\n" for T in T_cam0_camk))
    if times is not None:
        (path.parent / "times.txt").write_text("".join(f"{t:.6e}\n" for t in times))


def camera_forward(n: int, scale: float = 1.0) -> np.ndarray:
    """KITTI camera-0 poses driving straight ahead: 1 m (times scale) a frame along camera z."""
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, 2, 3] = scale * np.arange(n, dtype=float)
    return T


def run(argv: list[str], capsys) -> tuple[int, str, str]:
    rc = eval_cli.main(argv)
    out, err = capsys.readouterr()
    return rc, out, err


N_FILE = 61  # 60 m: short segments of 10..50 m


def test_cli_kitti_ground_truth_against_a_windowvo_tum_estimate(tmp_path, capsys):
    """KITTI camera 0 driving along its z is windowvo's base driving along x: a TUM estimate
    x = 1.02 i (identity rotation) against it is the scaled line, with its hand-computed t_rel."""
    write_kitti(tmp_path / "gt" / "poses.txt", camera_forward(N_FILE), 0.1 * np.arange(N_FILE))
    est = line(N_FILE, 1.02)
    write_tum(tmp_path / "trajectory.txt", est.timestamps, est.T_world_base, header="windowvo estimate\nT_world_base")
    rc, out, err = run([str(tmp_path / "gt" / "poses.txt"), str(tmp_path / "trajectory.txt"), "--json"], capsys)
    assert rc == 0, err
    d = json.loads(out)
    assert d["groundtruth_read"].startswith("KITTI poses (12 numbers/line") and "times from times.txt" in d[
        "groundtruth_read"]
    assert d["estimate_read"] == f"TUM (8 numbers/line), {N_FILE} poses"
    mean, _ = expected_scale_pct(N_FILE, 1.02, SegmentSet.SHORT.lengths_m)
    assert d["kitti_short"]["n_segments"] == 5 + 4 + 3 + 2 + 1
    assert d["kitti_short"]["t_rel_pct"] == pytest.approx(mean, rel=1e-6)
    assert d["kitti_devkit"]["n_segments"] == 0 and d["kitti_devkit"]["t_rel_pct"] is None
    rc, out, _ = run([str(tmp_path / "gt" / "poses.txt"), str(tmp_path / "trajectory.txt")], capsys)
    assert rc == 0
    assert f"ground truth: KITTI poses (12 numbers/line, camera 0 -> windowvo base), {N_FILE} poses, " \
           "times from times.txt" in out
    assert f"short segments 10-80 m: t_rel {mean:.2f} % | r_rel 0.000 deg/100 m" in out
    assert "KITTI devkit segments 100-800 m: n/a" in out


def test_cli_kitti_without_times_uses_the_frame_period(tmp_path, capsys):
    """No times.txt: frame index x --kitti-dt. Both files so: they match; against a TUM ground truth
    at 10 Hz, a 0.05 s period matches only every other pose and the CLI says why."""
    write_kitti(tmp_path / "a" / "poses.txt", camera_forward(N_FILE))
    write_kitti(tmp_path / "b" / "est.txt", camera_forward(N_FILE, 1.02))
    rc, out, _ = run([str(tmp_path / "a" / "poses.txt"), str(tmp_path / "b" / "est.txt")], capsys)
    assert rc == 0 and "times = frame index x 0.1 s (no times.txt beside it)" in out
    mean, _ = expected_scale_pct(N_FILE, 1.02, SegmentSet.SHORT.lengths_m)
    assert f"t_rel {mean:.2f} %" in out
    gt = line(N_FILE)
    write_tum(tmp_path / "gt.txt", gt.timestamps, gt.T_world_base)
    rc, out, err = run([str(tmp_path / "gt.txt"), str(tmp_path / "b" / "est.txt"), "--kitti-dt", "0.05"], capsys)
    assert rc == 0 and "times = frame index x 0.05 s" in out
    assert "note: only 31 poses matched" in err


def test_cli_format_override(tmp_path, capsys):
    write_kitti(tmp_path / "poses.txt", camera_forward(N_FILE))
    rc, _, err = run([str(tmp_path / "poses.txt"), str(tmp_path / "poses.txt"), "--gt-format", "tum"], capsys)
    assert rc == 2 and err.startswith("windowvo.eval: error:") and "expected 8 numbers" in err
    assert err.strip().count("\n") == 0
    rc, out, _ = run([str(tmp_path / "poses.txt"), str(tmp_path / "poses.txt"), "--est-format", "kitti"], capsys)
    assert rc == 0 and "(format forced)" in out


def test_cli_reads_cp1252_bytes_in_comments(tmp_path, capsys):
    """A 0xE9 (cp1252 e-acute, invalid UTF-8) in both files' headers; the estimate's header also
    says 'up to scale', so it is monocular (no ATE SE(3))."""
    gt = arc(121, 0.02)
    write_tum(tmp_path / "gt.txt", gt.timestamps, gt.T_world_base)
    write_tum(tmp_path / "est.txt", gt.timestamps, gt.T_world_base)
    for name, head in (("gt.txt", b"# caf\xe9 ground truth\n"), ("est.txt", b"# r\xe9sultat: up to scale\n")):
        p = tmp_path / name
        p.write_bytes(head + p.read_bytes())
        with pytest.raises(UnicodeDecodeError):
            p.read_text(encoding="utf-8")
    rc, out, err = run([str(tmp_path / "gt.txt"), str(tmp_path / "est.txt")], capsys)
    assert rc == 0, err
    assert "ATE SE(3) n/a" in out and "short segments 10-80 m: t_rel 0.00 %" in out


@pytest.mark.parametrize("case", ["missing", "empty", "columns", "comments_only"])
def test_cli_bad_files_are_one_line(tmp_path, capsys, case):
    gt = line(N_FILE)
    write_tum(tmp_path / "gt.txt", gt.timestamps, gt.T_world_base)
    bad = tmp_path / "bad.txt"
    expect = {"missing": "not found", "empty": "no poses", "columns": "got 5", "comments_only": "no poses"}[case]
    if case == "empty":
        bad.write_text("")
    elif case == "columns":
        bad.write_text("0 1 2 3 4\n")
    elif case == "comments_only":
        bad.write_text("# header\n#\n")
    for argv in ([str(tmp_path / "gt.txt"), str(bad)], [str(bad), str(tmp_path / "gt.txt")]):
        rc, out, err = run(argv, capsys)
        assert rc == 2 and out == "" and err.startswith("windowvo.eval: error:") and expect in err
        assert err.strip().count("\n") == 0


def test_cli_plot_to_a_missing_directory(tmp_path, capsys):
    gt = line(N_FILE)
    write_tum(tmp_path / "gt.txt", gt.timestamps, gt.T_world_base)
    rc, out, err = run([str(tmp_path / "gt.txt"), str(tmp_path / "gt.txt"), "--plot",
                        str(tmp_path / "nope" / "p.png")], capsys)
    assert rc == 2 and out == "" and "directory not found" in err and err.strip().count("\n") == 0
    rc, out, err = run([str(tmp_path / "gt.txt"), str(tmp_path / "gt.txt"), "--plot", str(tmp_path / "p.png")],
                       capsys)
    assert rc == 0 and (tmp_path / "p.png").stat().st_size > 0


def test_cli_plot_that_cannot_be_written(tmp_path, capsys, monkeypatch):
    """A write error (read-only directory, full disk) after the numbers: they stay printed, one error
    line, exit 2. Simulated, since root writes into a chmod 555 folder; the real folder case runs
    when not root."""
    gt = line(N_FILE)
    write_tum(tmp_path / "gt.txt", gt.timestamps, gt.T_world_base)

    def refuse(path, *args, **kwargs):
        raise PermissionError(13, "Permission denied", str(path))

    monkeypatch.setattr(eval_cli, "plot_trajectories", refuse)
    rc, out, err = run([str(tmp_path / "gt.txt"), str(tmp_path / "gt.txt"), "--plot", str(tmp_path / "p.png")],
                       capsys)
    assert rc == 2 and "short segments 10-80 m" in out
    assert err.strip() == f"windowvo.eval: error: cannot write the plot {tmp_path / 'p.png'}: Permission denied"


@pytest.mark.skipif(os.geteuid() == 0, reason="root can write into a read-only folder")
def test_cli_plot_into_a_read_only_directory(tmp_path, capsys):
    gt = line(N_FILE)
    write_tum(tmp_path / "gt.txt", gt.timestamps, gt.T_world_base)
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    rc, _, err = run([str(tmp_path / "gt.txt"), str(tmp_path / "gt.txt"), "--plot", str(ro / "p.png")], capsys)
    assert rc == 2 and "cannot write the plot" in err and err.strip().count("\n") == 0


def test_cli_subprocess_has_no_traceback(tmp_path):
    (tmp_path / "bad.txt").write_bytes(b"\xff\xfe 1 2\n")
    r = subprocess.run([sys.executable, "-m", "windowvo.eval", str(tmp_path / "bad.txt"), str(tmp_path / "bad.txt")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr and r.stderr.strip().count("\n") == 0


@pytest.mark.skipif(not (DATA / "poses.txt").is_file(), reason=f"KITTI excerpt not found: {DATA}")
def test_real_kitti_excerpt_against_itself_and_a_scaled_copy(tmp_path, capsys):
    """kitti06 frames 0-50 (59.8 m): against itself 0; against a copy with its translations x 1.02
    (times.txt copied beside it), every segment's error is 2% of the ground-truth chord of the
    segment, |p_last - p_first|, over L (rotations equal, so t(error) = -0.02 R^T (p_last - p_first))."""
    rc, out, _ = run([str(DATA / "poses.txt"), str(DATA / "poses.txt")], capsys)
    assert rc == 0 and "short segments 10-80 m: t_rel 0.00 % | r_rel 0.000 deg/100 m" in out
    rows = np.loadtxt(DATA / "poses.txt").reshape(-1, 3, 4)
    scaled = rows.copy()
    scaled[:, :, 3] *= 1.02
    T = np.tile(np.eye(4), (len(rows), 1, 1))
    T[:, :3, :] = scaled
    write_kitti(tmp_path / "poses.txt", T, np.loadtxt(DATA / "times.txt"))
    rc, out, _ = run([str(DATA / "poses.txt"), str(tmp_path / "poses.txt"), "--json", "--kitti-frame", "cam0"], capsys)
    d = json.loads(out)["kitti_short"]
    p = rows[:, :, 3]
    dist = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
    errs = [0.02 * np.linalg.norm(p[int(np.argmax(dist > dist[f] + L))] - p[f]) / L
            for f in range(0, len(p), 10) for L in SegmentSet.SHORT.lengths_m if dist[-1] > dist[f] + L]
    assert d["n_segments"] == len(errs) == 15
    assert d["t_rel_pct"] == pytest.approx(100.0 * np.mean(errs), rel=1e-5)
