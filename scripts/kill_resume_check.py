"""Kill -9 a run at random frames, repeatedly, and check what ``--resume`` makes of the folder.

For each repeat: a run of SEQUENCE is killed (SIGKILL) once its journal holds a random number of finished frames;
the folder must then hold a journal whose final keyframes cover every frame up to the last marginalised one, and
``python -m windowvo.run CONFIG --resume`` must write trajectory.txt, stats.csv, summary.json ("resumed": true) and
config_resolved.yaml, with the poses up to the last final keyframe equal to an uninterrupted run's.

    python scripts/kill_resume_check.py SEQUENCE_FOLDER WORK_FOLDER [--repeats 10] [--run-mode pipelined]
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from windowvo.io.trajectory import read_tum
from windowvo.runtime.journal import JOURNAL_NAME, last_final_frame, read_journal


def write_config(path: Path, seq: Path, out: Path, run_mode: str) -> None:
    path.write_text(f"sequence: {seq}\noutput: {out}\nrun_mode: {run_mode}\nviz:\n  rerun: 'off'\n")


def run(args: list[str], timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "windowvo.run", *args, "--no-progress", "-q"], capture_output=True,
                          text=True, timeout=timeout)


def frames_in(journal: Path) -> int:
    try:
        return journal.read_text().count('{"frame"')
    except OSError:
        return 0


def kill_at(cfg: Path, out: Path, n_frames: int, timeout: float = 600) -> float:
    """Start a run, SIGKILL it once its journal holds n_frames frames; returns the time of the kill (s)."""
    t0 = time.monotonic()
    proc = subprocess.Popen([sys.executable, "-m", "windowvo.run", str(cfg), "--no-progress", "-q"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    while proc.poll() is None and frames_in(out / JOURNAL_NAME) < n_frames:
        if time.monotonic() - t0 > timeout:
            break
        time.sleep(0.02)
    with_group = proc.poll() is None
    if with_group:
        os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)
    return time.monotonic() - t0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequence", type=Path)
    ap.add_argument("work", type=Path)
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--run-mode", default="pipelined")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    a.work.mkdir(parents=True, exist_ok=True)
    ref_cfg = a.work / "reference.yaml"
    write_config(ref_cfg, a.sequence.resolve(), (a.work / "reference").resolve(), a.run_mode)
    t = time.monotonic()
    r = run([str(ref_cfg), "--force"])
    assert r.returncode == 0, r.stderr
    wall_ref = time.monotonic() - t
    ref = read_tum(a.work / "reference" / "trajectory.txt")
    ref_ate = json.loads((a.work / "reference" / "summary.json").read_text())["accuracy"]["ate_se3_rmse_m"]
    n_total = len(ref)
    rng = random.Random(a.seed)
    failures = 0
    print(f"reference: {n_total} frames, {wall_ref:.1f} s, ATE SE(3) {ref_ate:.4f} m")
    for k in range(a.repeats):
        out = (a.work / f"killed-{k}").resolve()
        cfg = a.work / f"killed-{k}.yaml"
        write_config(cfg, a.sequence.resolve(), out, a.run_mode)
        if out.exists():
            run([str(cfg), "--force", "max_frames=1"])  # start clean (the old files moved aside)
            for f in out.iterdir():
                if f.is_file():
                    f.unlink()
        target = rng.randint(1, n_total - 1)
        t_kill = kill_at(cfg, out, target)
        j = read_journal(out / JOURNAL_NAME)
        last = last_final_frame(j)
        r = run([str(cfg), "--resume"])
        ok = r.returncode == 0
        msg = r.stderr.strip().splitlines()[-1:] if not ok else []
        if ok:
            traj = read_tum(out / "trajectory.txt")
            summary = json.loads((out / "summary.json").read_text())
            n_cover = 0 if last is None else last + 1
            same = len(traj) == len(j.records) and (n_cover == 0 or np.allclose(
                traj.T_world_base[:n_cover], ref.T_world_base[:n_cover], atol=1e-6))
            ok = same and summary.get("resumed") is True and (out / "stats.csv").is_file() and (
                out / "config_resolved.yaml").is_file()
            ate = (summary.get("accuracy") or {}).get("ate_se3_rmse_m")
            print(f"kill {k}: at {target} frames ({t_kill:.1f} s): journal {len(j.records)} frames, "
                  f"{len(j.final_keyframes)} final keyframes, smoothed through frame "
                  f"{None if last is None else j.records[last].frame_index}; resumed trajectory {len(traj)} poses, "
                  f"equal to the reference up to there: {same}; ATE of the part {ate}")
        else:
            print(f"kill {k}: at {target} frames: --resume failed: {msg}")
        failures += not ok
    print(f"{a.repeats - failures}/{a.repeats} kills resumed correctly")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
