"""The .rrd recording of a run, read back through Rerun's Python API (never the CLI)."""

import numpy as np
from conftest import make_config
from rerun.chunk import RrdReader

from windowvo.app import run_job
from windowvo.io.trajectory import read_tum


def test_recording_matches_outputs(short_loop, tmp_path):
    cfg = make_config(short_loop, tmp_path / "out", viz={"rerun": "save", "image_every": 1}, max_frames=80)
    rep = run_job(cfg)
    rrd = tmp_path / "out" / "recording.rrd"
    assert rrd.is_file()
    paths: dict[str, int] = {}
    chunks = list(RrdReader(str(rrd)).stream())
    for ch in chunks:
        paths[str(ch.entity_path)] = paths.get(str(ch.entity_path), 0) + ch.num_rows
    for expected in ["/world/estimate/base/cam/image", "/world/estimate/base/cam/tracks", "/world/estimate/base",
                     "/world/landmarks", "/world/groundtruth", "/world/wheel_odometry", "/plots/tracked_features",
                     "/plots/backend_ms", "/plots/inlier_ratio"]:
        assert expected in paths, (expected, sorted(paths))
    assert paths["/world/estimate/base/cam/image"] == rep.result.n_frames == 80
    assert paths["/plots/tracked_features"] == 80
    traj = read_tum(tmp_path / "out" / "trajectory.txt")
    assert len(traj) == 80
    # the last logged position of the estimate is the last line of trajectory.txt
    rows = []
    for ch in chunks:
        if str(ch.entity_path) == "/world/estimate/base" and not ch.is_static:
            rb = ch.to_record_batch()
            frames = rb.column("frame").to_pylist()
            trans = rb.column("Transform3D:translation").to_pylist()
            rows.extend((f, row_id, t[0]) for row_id, (f, t) in enumerate(zip(frames, trans)) if t)
    assert rows
    last = max(rows, key=lambda r: (r[0], r[1]))
    assert last[0] == 79
    assert np.allclose(last[2], traj.positions[-1], atol=1e-4), (last, traj.positions[-1])
