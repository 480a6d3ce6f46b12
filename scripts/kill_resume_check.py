"""Kill -9 a run at random frames, repeatedly, and check that ``--resume`` completes it as well as a run that was not.

For each repeat: a run of SEQUENCE is killed (SIGKILL) once its journal holds a random number of finished frames;
the folder must then hold a journal whose final keyframes cover every frame up to the last marginalised one, and
``python -m windowvo.run CONFIG --resume`` must continue the run to the end of the sequence: trajectory.txt with
every frame (the poses up to the last final keyframe equal to an uninterrupted run's), stats.csv with every frame,
summary.json ("resumed": true, "interrupted": false) and config_resolved.yaml, and an ATE (SE(3) RMSE) within
--max-ratio (1.05) of the uninterrupted run's. Prints one row per repeat; exits 1 if any repeat fails.

    python scripts/kill_resume_check.py SEQUENCE_FOLDER WORK_FOLDER [--repeats 10] [--run-mode pipelined]
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
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


@dataclass
class Repeat:
    """One kill and its resume."""

    kill_frames: int  # frames in the journal when the run was killed
    journal_frames: int
    last_final: int | None  # frame index of the journal's last final keyframe
    resumed_from: int | None = None
    ate: float | None = None
    error: str = ""

    def row(self, k: int, ref_ate: float) -> str:
        ratio = f"{self.ate / ref_ate:.3f}" if self.ate is not None else "-"
        ate = f"{self.ate:.4f}" if self.ate is not None else "-"
        return (f"| {k} | {self.kill_frames} | {self.journal_frames} | {self.last_final} | {self.resumed_from} | "
                f"{ref_ate:.4f} | {ate} | {ratio} | {self.error or 'ok'} |")


def check_resumed(out: Path, rep: Repeat, ref, n_cover: int, max_ratio: float, ref_ate: float) -> Repeat:
    """The resumed folder: every frame, the prefix equal to the reference, the ATE within max_ratio."""
    traj = read_tum(out / "trajectory.txt")
    summary = json.loads((out / "summary.json").read_text())
    rep.resumed_from = summary.get("resumed_from_frame")
    rep.ate = (summary.get("accuracy") or {}).get("ate_se3_rmse_m")
    n_stats = len((out / "stats.csv").read_text().splitlines()) - 1
    if len(traj) != len(ref) or n_stats != len(ref):
        rep.error = f"{len(traj)} poses, {n_stats} stats rows, not {len(ref)}"
    elif n_cover and not np.allclose(traj.T_world_base[:n_cover], ref.T_world_base[:n_cover], atol=1e-6):
        rep.error = "prefix differs from the uninterrupted run"
    elif summary.get("resumed") is not True or summary.get("interrupted") is not False:
        rep.error = "summary.json not resumed/complete"
    elif not (out / "config_resolved.yaml").is_file():
        rep.error = "no config_resolved.yaml"
    elif rep.ate is None or rep.ate > max_ratio * ref_ate:
        rep.error = f"ATE ratio above {max_ratio}"
    return rep


def one_repeat(k: int, a: argparse.Namespace, target: int, ref, ref_ate: float) -> Repeat:
    out = (a.work / f"killed-{k}").resolve()
    cfg = a.work / f"killed-{k}.yaml"
    write_config(cfg, a.sequence.resolve(), out, a.run_mode)
    if out.exists():
        shutil.rmtree(out)
    kill_at(cfg, out, target)
    j = read_journal(out / JOURNAL_NAME)
    last = last_final_frame(j)
    rep = Repeat(target, len(j.records), None if last is None else j.records[last].frame_index)
    r = run([str(cfg), "--resume"])
    if r.returncode != 0:
        rep.error = f"--resume exit {r.returncode}: {r.stderr.strip().splitlines()[-1:]}"
        return rep
    return check_resumed(out, rep, ref, 0 if last is None else last + 1, a.max_ratio, ref_ate)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequence", type=Path)
    ap.add_argument("work", type=Path)
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--run-mode", default="pipelined")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--max-ratio", type=float, default=1.05, help="largest ATE resumed / uninterrupted accepted")
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
    rng = random.Random(a.seed)
    print(f"reference ({a.run_mode}): {len(ref)} frames, {wall_ref:.1f} s, ATE SE(3) {ref_ate:.4f} m\n")
    print("| repeat | killed at (journaled frames) | journal frames | last final kf | resumed from | "
          "ATE uninterrupted (m) | ATE resumed (m) | ratio | check |")
    print("|---|---|---|---|---|---|---|---|---|")
    failures = 0
    for k in range(a.repeats):
        rep = one_repeat(k, a, rng.randint(1, len(ref) - 1), ref, ref_ate)
        print(rep.row(k, ref_ate), flush=True)
        failures += bool(rep.error)
    print(f"\n{a.repeats - failures}/{a.repeats} kills resumed to the end within {a.max_ratio}x the ATE")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
