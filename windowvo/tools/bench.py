"""``python -m windowvo.bench``: accuracy, speed and memory against baselines, in one run.

Suites:

* ``sequences`` (default): rendered synthetic sequences (loop, figure eight with vibration,
  ramp, stop-and-go, wheel slip, loops whose wheels report 2% too much and 3% too little
  distance, and a figure eight rocking by 1 deg whose wheels report 3% too little) and the
  KITTI excerpts in ``../shared/data`` when present (synthetic wheels with a 1% and with a 2%
  scale error). None of the wheel errors is told to the estimator.
  For each: windowvo (its smoothed and its causal, online trajectory), windowvo a second
  time without the ground-plane cue and without online wheel calibration (the behaviour
  before the metric-scale work; back-end time of both runs, so the cue's cost shows), and,
  in the same process, wheel odometry alone and frame-to-frame essential-matrix chaining
  scaled by wheel distance. Prints a markdown table, writes ``bench.json`` and a PNG per
  sequence overlaying the trajectories.
* ``frontend``: front-end time per 640x480 frame on preloaded images.
* ``backend``: back-end time per keyframe (median, p95) on feature-level data with a
  20-keyframe window, and resident memory after 500 and after N keyframes.
* ``rerun``: run time with the Rerun recording on and off.
* ``memory``: peak RSS of a whole run over 500 frames and over 5,000 frames (rendered once).
* ``bag``: peak RSS of a run on a ROS bag (mcap) of a rendered loop and on a bag 10 times as
  large (frames are streamed from the bag, so memory should stay flat).
* ``stages``: the per-stage CPU budget (decode, gain normalisation, tracking, detection, undistortion,
  RANSAC, keyframe decision, each back-end step, recording, outputs) per frame and per keyframe, on a
  640x480 loop and a KITTI-size sequence, and the start-up (``windowvo/tools/stage_budget.py``; also
  written to ``stages/stages.json``).
* ``speed``: whole processes as a user runs them (``python -m windowvo.run``, default run mode, recording
  saved) against the frame-to-frame chaining baseline (ORB 2000) as a whole process, back to back and
  alternated, ``--repeats`` pairs (the fastest of each counts), on the rendered 640x480 loop and figure eight
  (30 s) and the KITTI excerpts (``windowvo/tools/speed.py``): wall and CPU time, the ratio, each one's ATE.

Each sequence runs in its own process (``--jobs N`` runs N at once) so peak RSS is per run.
``--set KEY=VALUE`` (repeatable) changes the config of every windowvo run of the ``sequences``
and ``scale`` suites (the scale suite's cue switches of each way still apply), e.g.
``--set backend.marginalize_every=1`` to compare a setting against the defaults.
Numbers are what this machine measured; nothing is enforced here.
"""

from __future__ import annotations

import enum
import os
import resource
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..config import apply_overrides, config_from_dict
from .kitti_columns import cell, kitti_errors, shown_columns

SHARED_DATA = Path(__file__).resolve().parents[3] / "shared" / "data"  # ../shared/data beside the repository
KITTI_EXCERPTS = ("kitti06_000-050", "kitti01_000-050")  # the real excerpts the suites run, in SHARED_DATA


# The run "without ground cue": windowvo as it was before the metric-scale work (#11).
NO_GROUND_CUE: dict = {"backend": {"ground": {"enabled": False}, "wheel_calibration": {"enabled": False}}}
# Synthetic wheels on KITTI (no wheels there): the earlier bench setting and the issue's (#11).
KITTI_WHEEL_SCALE_ERRORS = (0.01, 0.02)
KITTI_WHEEL_YAW_BIAS_PER_M = 0.005


class CaseKind(str, enum.Enum):
    """Where a benchmark sequence comes from."""

    SYNTH = "synth"  # rendered (windowvo.synth)
    KITTI = "kitti"  # a KITTI excerpt in ../shared/data


@dataclass
class SeqCase:
    name: str
    kind: CaseKind
    spec: dict | None = None
    path: Path | None = None
    kitti_wheel_scale_error: float | None = 0.01  # KITTI only: scale error of the synthetic wheels (None: no wheels)

    @property
    def wheel_scale_error(self) -> float | None:
        """The wheels' distance scale error (reported = (1 + e) * true; None: no wheels, a monocular run);
        the estimator is not told."""
        if self.kind is CaseKind.KITTI:
            return self.kitti_wheel_scale_error
        from ..synth.generate import WheelErrorModel

        return float((self.spec or {}).get("wheel", WheelErrorModel()).scale_error)


def synthetic_cases(duration: float) -> list[SeqCase]:
    from ..synth.generate import WheelErrorModel
    from ..synth.paths import PathKind

    return [
        SeqCase("loop", CaseKind.SYNTH, dict(path=PathKind.LOOP, duration_s=duration, seed=31)),
        SeqCase("figure_eight_vibration", CaseKind.SYNTH,
                dict(path=PathKind.FIGURE_EIGHT, duration_s=duration, seed=32, vibration_deg=1.5)),
        SeqCase("ramp", CaseKind.SYNTH, dict(path=PathKind.RAMP, duration_s=duration, seed=33)),
        SeqCase("stop_and_go", CaseKind.SYNTH, dict(path=PathKind.STOP_AND_GO, duration_s=duration, seed=34, image_noise=1.0)),
        SeqCase("wheel_slip", CaseKind.SYNTH, dict(path=PathKind.LOOP, duration_s=duration, seed=35,
                                            wheel=WheelErrorModel(slip_windows=[(8.0, 10.0, 0.4), (20.0, 21.5, 0.5)]))),
        SeqCase("loop_wheels+2pct", CaseKind.SYNTH, dict(path=PathKind.LOOP, duration_s=duration, seed=36,
                                                  wheel=WheelErrorModel(scale_error=0.02))),
        SeqCase("loop_wheels-3pct", CaseKind.SYNTH, dict(path=PathKind.LOOP, duration_s=duration, seed=37,
                                                  wheel=WheelErrorModel(scale_error=-0.03))),
        # A rocking base with a large wheel error: the online calibration's known weak spot (docs/performance.md).
        SeqCase("figure_eight_vibration_wheels-3pct", CaseKind.SYNTH,
                dict(path=PathKind.FIGURE_EIGHT, duration_s=duration, seed=62, vibration_deg=1.0,
                     wheel=WheelErrorModel(scale_error=-0.03))),
        # A camera mount pitched 1 deg off its calibration: the ground cue's scale pays for it until the
        # learnt floor tilt is significant (backend.ground.mount_calibration auto) and after, if it is off.
        SeqCase("loop_mount_pitch+1deg", CaseKind.SYNTH,
                dict(path=PathKind.LOOP, duration_s=duration, seed=63, calib_pitch_error_deg=1.0)),
    ]


def kitti_cases() -> list[SeqCase]:
    """Each excerpt once per synthetic wheel scale error (the first keeps the excerpt's name), and once
    without wheels (monocular: the road at camera 0's height is the only scale source)."""
    out = []
    for name in KITTI_EXCERPTS:
        if (SHARED_DATA / name).is_dir():
            for i, err in enumerate(KITTI_WHEEL_SCALE_ERRORS):
                case_name = name if i == 0 else f"{name}_wheels{100 * err:+.0f}pct"
                out.append(SeqCase(case_name, CaseKind.KITTI, path=SHARED_DATA / name, kitti_wheel_scale_error=err))
            out.append(SeqCase(f"{name}_monocular", CaseKind.KITTI, path=SHARED_DATA / name, kitti_wheel_scale_error=None))
    return out


def peak_rss_mb() -> float:
    """Peak resident memory of this process image (Linux ``VmHWM``).

    Not ``getrusage``: its ``ru_maxrss`` survives fork and exec, so a worker started by the
    bench would report the bench's own peak (e.g. from rendering) whenever that is larger.
    """
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _acc_row(acc) -> dict:
    if acc is None:
        return {}
    return {"ate_se3_m": float("nan") if acc.monocular else acc.ate_se3_rmse_m, "ate_sim3_m": acc.ate_sim3_rmse_m,
            "sim3_scale": acc.sim3_scale, "rpe_m_per_m": acc.rpe_trans_per_m,
            "end_drift_pct": acc.end_drift_pct, "path_m": acc.path_length_m}


def _method_row(acc, groundtruth, trajectory, metric: bool = True) -> dict:
    """A method's accuracy row with its KITTI relative errors (``kitti``: both segment sets; an estimate up to
    scale is scaled by its Sim(3) scale first)."""
    if acc is None:
        return {}
    return {**_acc_row(acc), "kitti": kitti_errors(groundtruth, trajectory, None if metric else acc.sim3_scale)}


def _median(ms: list[float]) -> float:
    return float(np.median(ms)) if ms else float("nan")


def _scale_row(r) -> dict:
    """What fixed a run's scale and, with online calibration, the wheels' final estimate."""
    c = r.wheel_calibration
    return {"metric": r.metric, "scale_sources": list(r.scale_sources),
            "wheel_calibration": None if c is None else {
                "scale": c.scale, "scale_sigma": c.scale_sigma,
                "yaw_bias_per_m": c.yaw_bias_per_m, "yaw_bias_sigma": c.yaw_bias_sigma,
                "yaw_scale": c.yaw_scale, "yaw_scale_sigma": c.yaw_scale_sigma}}


def _deep_merge(base: dict, extra: dict) -> dict:
    out = dict(base)
    for k, v in extra.items():
        out[k] = _deep_merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def ensure_rendered(case: SeqCase, cache: Path) -> Path:
    """Render a synthetic case once into the cache (reused by later runs)."""
    from ..synth.generate import SynthSpec, generate_sequence

    seq_dir = cache / case.name
    if case.spec is None:
        raise ValueError(f"synthetic bench case {case.name!r} has no spec")
    if not (seq_dir / "synth.json").is_file():
        generate_sequence(seq_dir, SynthSpec(**case.spec))
    return seq_dir


def case_config_data(case: SeqCase, cache: Path, out_root: Path, rerun: bool = False,
                     overrides: tuple[str, ...] = ()) -> dict:
    """The config mapping of a case's run with the ground cue (the defaults, changed by ``overrides``:
    ``dotted.key=value`` as on the run's command line); renders a synthetic case. Sequential mode, so
    each stage's timing is its own (``--suite modes`` measures the pipelined run)."""
    data: dict = {"progress": False, "viz": {"rerun": "save" if rerun else "off"}, "run_mode": "sequential"}
    if case.kind is CaseKind.SYNTH:
        seq_dir = ensure_rendered(case, cache)
        data["sequence"] = str(seq_dir)
    else:
        data.update(sequence=str(case.path), dataset="kitti")
        if case.kitti_wheel_scale_error is not None:
            data["odometry_synthesis"] = {"enabled": True, "scale_error": case.kitti_wheel_scale_error,
                                          "yaw_bias_per_m": KITTI_WHEEL_YAW_BIAS_PER_M}
    data["output"] = str(out_root / case.name)
    return apply_overrides(data, list(overrides))


def _run_without_ground_cue(data: dict, out: Path):
    """The same sequence without the ground cue and without online wheel calibration (``NO_GROUND_CUE``)."""
    from ..config import config_from_dict
    from ..runtime.job import run_job

    cfg_nc = config_from_dict(_deep_merge(data, {**NO_GROUND_CUE, "output": str(out / "no_ground_cue"),
                                                 "viz": {"rerun": "off"}}))
    rep_nc = run_job(cfg_nc)
    r_nc = rep_nc.result
    row = {
        "frames": r_nc.n_frames,
        "keyframes": r_nc.n_keyframes,
        "fps": r_nc.fps,
        "backend_ms_median": _median(r_nc.backend_ms),
        "backend_ms_p95": float(np.percentile(r_nc.backend_ms, 95)) if r_nc.backend_ms else float("nan"),
        "resets": r_nc.n_resets,
        "windowvo": _acc_row(rep_nc.accuracy),
        "windowvo_online": _acc_row(rep_nc.online_accuracy),
        "scale": _scale_row(r_nc),
    }
    return row, r_nc


def run_case(case: SeqCase, cache: Path, out_root: Path, rerun: bool = False,
             overrides: tuple[str, ...] = ()) -> dict:
    """One sequence (runs in a worker process): windowvo, windowvo without the ground cue and
    online wheel calibration (``NO_GROUND_CUE``, outputs in ``no_ground_cue/``), both baselines."""
    import logging

    logging.basicConfig(level=logging.ERROR)
    from ..errors import SequenceError
    from ..eval.baselines import essential_chaining
    from ..eval.metrics import evaluate, plot_trajectories
    from ..runtime.job import run_job, wheel_only_trajectory
    data = case_config_data(case, cache, out_root, rerun, overrides)
    out = out_root / case.name
    rep = run_job(config_from_dict(data))
    r, seq = rep.result, rep.sequence
    gt = seq.groundtruth
    if gt is None:
        raise SequenceError(f"bench sequence {case.name!r} has no ground truth")
    row: dict = {
        "sequence": case.name,
        "kind": case.kind.value,
        "wheel_scale_error": case.wheel_scale_error,
        "frames": r.n_frames,
        "keyframes": r.n_keyframes,
        "fps": r.fps,
        "frontend_ms_mean": float(np.mean(r.frontend_ms)) if r.frontend_ms else float("nan"),
        "backend_ms_median": _median(r.backend_ms),
        "backend_ms_p95": float(np.percentile(r.backend_ms, 95)) if r.backend_ms else float("nan"),
        "peak_rss_mb": peak_rss_mb(),  # before the second run, so it is this run's
        "resets": r.n_resets,
        "windowvo": _method_row(rep.accuracy, gt, r.trajectory, r.metric),
        "windowvo_online": _acc_row(rep.online_accuracy),
        "scale": _scale_row(r),
    }
    row["no_ground_cue"], r_nc = _run_without_ground_cue(data, out)
    base_ms = row["no_ground_cue"]["backend_ms_median"]
    row["backend_cue_cost_pct"] = 100.0 * (row["backend_ms_median"] / base_ms - 1.0) if base_ms > 0 else float("nan")
    wheel = wheel_only_trajectory(seq, r.trajectory.timestamps)
    row["wheel"] = _method_row(evaluate(gt, wheel), gt, wheel) if wheel is not None else {}
    # The chaining baseline takes its scale from the wheels: none without them.
    chain = essential_chaining(seq) if seq.odometry is not None else None
    row["chaining"] = _method_row(evaluate(gt, chain.trajectory), gt, chain.trajectory) if chain is not None else {}
    row["chaining_fps"] = chain.fps if chain is not None else float("nan")
    row["chaining_failed_steps"] = chain.n_failed_steps if chain is not None else 0
    estimates = {"windowvo": r.trajectory}
    if r.trajectory_online is not None:
        estimates["windowvo online (causal)"] = r.trajectory_online
    estimates["windowvo without ground cue"] = r_nc.trajectory
    if wheel is not None:
        estimates["wheel odometry"] = wheel
    if chain is not None:
        estimates["E-matrix chaining"] = chain.trajectory
    plot_trajectories(out / "trajectories.png", gt, estimates, title=case.name)
    return row


SEQUENCE_COLUMNS = (
    "sequence", "method", "frames", "fps", "front-end ms/frame", "back-end ms/kf (median / p95)",
    "back-end ms/kf median without ground cue (cue cost)", "peak RSS MB", "ATE SE(3) m",
    "online (causal) ATE SE(3) m", "ATE SE(3) without ground cue m", "ATE Sim(3) m", "RPE m/m", "end drift %",
    "wheel scale error: true / estimated",
)


def _f(v, fmt: str) -> str:
    """A number for the table; blank when missing or not finite."""
    if v is None or not np.isfinite(v):
        return ""
    return format(v, fmt)


def sequences_caption(rows: list[dict]) -> str:
    """Which wheels each sequence had (none of this is told to the estimator) and what the columns compare."""
    groups: dict[tuple[str, float | None], list[str]] = {}
    for r in rows:
        groups.setdefault((r.get("kind", CaseKind.SYNTH.value), r["wheel_scale_error"]), []).append(r["sequence"])
    parts = []
    for (kind, err), names in sorted(groups.items(), key=lambda kv: (kv[0][0] != CaseKind.SYNTH.value, kv[0][1] is None,
                                                                     kv[0][1] or 0.0)):
        if err is None:
            parts.append(f"no wheels (monocular, the floor at the camera height is the only scale source): "
                         f"{', '.join(names)}")
            continue
        what = ("rendered wheels" if kind == CaseKind.SYNTH.value else
                f"KITTI, synthetic wheels (yaw bias {KITTI_WHEEL_YAW_BIAS_PER_M} rad/m)")
        parts.append(f"{what} with a {100 * err:+.0f}% scale error: {', '.join(names)}")
    return ("Wheel odometry (reported distance = (1 + scale error) x true; the estimator is not told): "
            + "; ".join(parts) + ". Rendered wheels also drift 0.01 rad/m in heading; wheel_slip adds slip "
            "windows. \"Without ground cue\": the same sequence run again with backend.ground.enabled=false "
            "and backend.wheel_calibration.enabled=false (before the metric-scale work); cue cost: back-end "
            "median with the cue / without - 1. ATE SE(3): the smoothed trajectory (trajectory.txt); online: "
            "the causal one (trajectory_online.txt). Estimated scale error: the online wheel calibration at the end. "
            "t_rel / r_rel: the KITTI odometry metric (mean translational error in % and rotational error in "
            "deg/100 m) over segments of 10-80 m of the smoothed trajectory (100-800 m, the devkit's, when a path "
            "is long enough; n/a: too short); a run up to scale is scaled by its Sim(3) scale first.")


METHODS = {"windowvo": "windowvo", "wheel": "wheel odometry", "chaining": "E-matrix chaining"}


def _windowvo_cells(r: dict) -> dict[str, str]:
    """The cells only windowvo's line of a sequence has (speed, cue cost, online ATE, wheel calibration)."""
    nc = r.get("no_ground_cue") or {}
    calib: dict | None = (r.get("scale") or {}).get("wheel_calibration")
    return {
        "fps": _f(r["fps"], ".1f"),
        "front-end ms/frame": _f(r["frontend_ms_mean"], ".2f"),
        "back-end ms/kf (median / p95)": f"{_f(r['backend_ms_median'], '.1f')} / {_f(r['backend_ms_p95'], '.1f')}",
        "back-end ms/kf median without ground cue (cue cost)":
            f"{_f(nc.get('backend_ms_median'), '.1f')} ({_f(r.get('backend_cue_cost_pct'), '+.0f')}%)" if nc else "",
        "peak RSS MB": _f(r["peak_rss_mb"], ".0f"),
        "online (causal) ATE SE(3) m": _f((r.get("windowvo_online") or {}).get("ate_se3_m"), ".3f"),
        "ATE SE(3) without ground cue m": _f((nc.get("windowvo") or {}).get("ate_se3_m"), ".3f"),
        "wheel scale error: true / estimated":
            "no wheels" if r["wheel_scale_error"] is None else
            f"{100 * r['wheel_scale_error']:+.1f}% / " + (f"{100 * (calib['scale'] - 1.0):+.1f}%" if calib else "-"),
    }


def sequences_table(rows: list[dict]) -> str:
    """The markdown table: a line per sequence and method, with the KITTI relative errors over 10-80 m (and
    over the devkit's 100-800 m when some ground-truth path is long enough for one such segment)."""
    kitti_cols = shown_columns([(r.get(m) or {}).get("kitti") for r in rows for m in METHODS])
    columns = (*SEQUENCE_COLUMNS[:-1], *(c.header for c in kitti_cols), SEQUENCE_COLUMNS[-1])
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    for r in rows:
        for method, name in METHODS.items():
            a = r.get(method) or {}
            cells = {c: "" for c in columns}
            cells.update({"sequence": r["sequence"], "method": name, "frames": str(r["frames"])})
            if method == "windowvo":
                cells.update(_windowvo_cells(r))
            elif method == "chaining":
                cells["fps"] = _f(r["chaining_fps"], ".1f")
            cells.update({
                "ATE SE(3) m": _f(a.get("ate_se3_m"), ".3f"),
                "ATE Sim(3) m": _f(a.get("ate_sim3_m"), ".3f"),
                "RPE m/m": _f(a.get("rpe_m_per_m"), ".3f"),
                "end drift %": _f(a.get("end_drift_pct"), ".2f"),
                **{c.header: cell(a.get("kitti"), c) for c in kitti_cols},
            })
            lines.append("| " + " | ".join(cells[c] for c in columns) + " |")
    return "\n".join(lines)


def run_cases_in_processes(cases: list[SeqCase], cache: Path, out: Path, jobs: int,
                           overrides: tuple[str, ...] = ()) -> list[dict]:
    """Each case in a fresh interpreter (``jobs`` at once, windowvo.executors); failures are reported and dropped."""
    from .executors import values_in_processes

    return values_in_processes([(c.name, run_case, (c, cache, out, False, tuple(overrides))) for c in cases], jobs,
                               "bench")


# ---------------------------------------------------------------------------- component suites


def bench_frontend(cache: Path, n_frames: int = 300) -> dict:
    from ..config import FrontendConfig, GateConfig, KeyframeConfig
    from ..frontend.frontend import Frontend
    from ..io.sequence import load_native
    from ..synth.generate import SynthSpec, generate_sequence
    from ..synth.paths import PathKind
    from ..types import Frame

    d = cache / "frontend_loop"
    if not (d / "synth.json").is_file():
        generate_sequence(d, SynthSpec(path=PathKind.LOOP, duration_s=n_frames / 20.0, seed=41))
    seq = load_native(d)
    imgs = [seq.read_image(i) for i in range(min(n_frames, len(seq)))]
    out = {}
    for tracker in ("klt", "orb"):
        fe = Frontend(seq.camera, FrontendConfig(tracker=tracker), KeyframeConfig(), GateConfig())
        ms_list: list[float] = []
        for i, im in enumerate(imgs):
            t0 = time.perf_counter()
            fe.process(Frame(i, float(seq.timestamps[i]), im))
            ms_list.append((time.perf_counter() - t0) * 1000)
        ms = np.asarray(ms_list[1:])
        out[tracker] = {"frames": len(ms), "mean_ms": float(ms.mean()), "median_ms": float(np.median(ms)),
                        "p95_ms": float(np.percentile(ms, 95)), "fps": float(1000.0 / ms.mean())}
    return out


def _rss_now_mb() -> float:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def bench_backend(n_keyframes: int = 5000) -> dict:
    from ..backend.smoother import OdometryStep, SlidingWindowBackend
    from ..config import BackendConfig
    from ..synth.features import simulate_features
    from ..synth.generate import SynthSpec
    from ..synth.paths import PathKind

    spacing = 0.4
    duration = 1.2 * n_keyframes * spacing / 0.8 + 5.0
    fs = simulate_features(SynthSpec(path=PathKind.LOOP, duration_s=duration, speed=0.8, seed=43),
                           keyframe_spacing_m=spacing)
    cfg = BackendConfig(window_keyframes=20)
    be = SlidingWindowBackend(fs.world.camera, cfg, use_odometry=True)
    ms_list: list[float] = []
    rss: dict[int, float] = {}
    lms: list[int] = []
    kfs = fs.keyframes[:n_keyframes]
    for i, fo in enumerate(kfs):
        odom = None
        if i > 0:
            t0, t1 = kfs[i - 1].timestamp, fo.timestamp
            odom = OdometryStep(fs.odometry.delta(t0, t1), fs.odometry.distance(t0, t1))
        bo = be.add_keyframe(fo, odom)
        ms_list.append(bo.backend_ms)
        lms.append(bo.n_landmarks)
        if i + 1 in (500, 1000, 2000, len(kfs)):
            rss[i + 1] = _rss_now_mb()
    ms = np.asarray(ms_list)
    return {"keyframes": len(kfs), "window": cfg.window_keyframes, "landmarks_median": float(np.median(lms)),
            "observations_per_keyframe": float(np.mean([len(f.track_ids) for f in kfs])),
            "median_ms": float(np.median(ms)), "p95_ms": float(np.percentile(ms, 95)),
            "rss_mb_after": {str(k): v for k, v in rss.items()}, "resets": be.n_resets}


def _run_peak_rss(seq_dir: str, out: str, max_frames: int) -> dict:
    import logging

    logging.basicConfig(level=logging.ERROR)
    from ..runtime.job import run_job

    cfg = config_from_dict({"sequence": seq_dir, "output": out, "progress": False, "viz": {"rerun": "off"},
                            "max_frames": max_frames})
    rep = run_job(cfg)
    return {"frames": rep.result.n_frames, "keyframes": rep.result.n_keyframes, "fps": rep.result.fps,
            "peak_rss_mb": peak_rss_mb()}


def bench_memory(cache: Path, out_root: Path, long_frames: int = 5000) -> dict:
    """Peak RSS of a whole pipeline run over 500 frames and over ``long_frames`` frames."""
    from ..synth.generate import SynthSpec, generate_sequence
    from ..synth.paths import PathKind

    d = cache / f"memory_loop_{long_frames}"
    if not (d / "synth.json").is_file():
        generate_sequence(d, SynthSpec(path=PathKind.FIGURE_EIGHT, duration_s=(long_frames - 1) / 20.0, seed=44))
    res = {}
    for n in (500, long_frames):
        with ProcessPoolExecutor(max_workers=1) as ex:
            res[str(n)] = ex.submit(_run_peak_rss, str(d), str(out_root / f"memory_{n}"), n).result()
    res["growth_pct"] = 100.0 * (res[str(long_frames)]["peak_rss_mb"] / res["500"]["peak_rss_mb"] - 1.0)
    return res


def children_cpu_s() -> float:
    """CPU seconds (user + system) of this process's children that have ended (and been waited for)."""
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return kids.ru_utime + kids.ru_stime


def cpu_with_children_s() -> float:
    """CPU seconds (user + system) of this process's threads and of its children that have ended."""
    own = resource.getrusage(resource.RUSAGE_SELF)
    return own.ru_utime + own.ru_stime + children_cpu_s()


def _rerun_job(seq_dir: str, out: str, on: bool) -> dict:
    """One whole job in a fresh process (so rerun's import counts): wall and CPU time, recording size."""
    import logging

    logging.basicConfig(level=logging.ERROR)
    t0, cpu0 = time.perf_counter(), cpu_with_children_s()
    from ..runtime.job import run_job

    cfg = config_from_dict({"sequence": seq_dir, "output": out, "progress": False,
                            "viz": {"rerun": "save" if on else "off"}})
    rep = run_job(cfg)
    wall = time.perf_counter() - t0
    row = {"frames": rep.result.n_frames, "wall_s": wall, "pipeline_s": rep.result.wall_s,
           "cpu_s": cpu_with_children_s() - cpu0,  # with the back-end process of the pipelined run
           "image_every": cfg.viz.image_every, "jpeg_quality": cfg.viz.jpeg_quality}
    rrd = Path(out) / "recording.rrd"
    if on:
        from rerun.chunk import RrdReader

        row["size_mb"] = rrd.stat().st_size / 1e6
        for ch in RrdReader(str(rrd)).stream():
            if str(ch.entity_path) == "/__properties/run":
                row["viewer_busy_s"] = float(ch.to_record_batch().column("viewer_busy_s").to_pylist()[-1][0])
    return row


def _mode_job(seq_dir: str, out: str, mode: str, rerun: str) -> dict:
    """One whole job in a fresh process: end-to-end fps of a run mode, and its trajectory file."""
    import logging

    logging.basicConfig(level=logging.ERROR)
    from ..runtime.job import run_job

    cfg = config_from_dict({"sequence": seq_dir, "output": out, "progress": False, "run_mode": mode,
                            "viz": {"rerun": rerun}})
    # CPU of every thread of this process and of its (joined) back-end worker, over the whole job.
    cpu0, t0 = cpu_with_children_s(), time.perf_counter()
    rep = run_job(cfg)
    job_wall, job_cpu = time.perf_counter() - t0, cpu_with_children_s() - cpu0
    r = rep.result
    return {"mode": mode, "rerun": rerun, "frames": r.n_frames, "keyframes": r.n_keyframes, "fps": r.fps,
            "job_cpu_s": job_cpu, "job_wall_s": job_wall, "cores_busy": job_cpu / job_wall,
            "backend_ms_median": float(np.median(r.backend_ms)) if r.backend_ms else float("nan"),
            "ate_se3_m": rep.accuracy.ate_se3_rmse_m if rep.accuracy is not None else float("nan"),
            "trajectory": (Path(out) / "trajectory.txt").read_text()}


def _chaining_fps(seq_dir: str) -> float:
    from ..eval.baselines import essential_chaining
    from ..io.sequence import load_native

    return float(essential_chaining(load_native(Path(seq_dir))).fps)


def bench_modes(cache: Path, out_root: Path, repeats: int = 3) -> dict:
    """End-to-end fps of the pipelined and the sequential run on the 30 s loop (default config, with and
    without the Rerun recording), each job in a fresh process, alternated, fastest of ``repeats``; the
    chaining baseline's fps on the same sequence; and whether the trajectories are identical."""
    case = synthetic_cases(30.0)[0]
    seq_dir = str(ensure_rendered(case, cache))
    res: dict = {}
    for rerun in ("save", "off"):
        runs: dict[str, list[dict]] = {"sequential": [], "pipelined": []}
        for _ in range(repeats):
            for mode in ("sequential", "pipelined"):
                with ProcessPoolExecutor(max_workers=1) as ex:
                    runs[mode].append(ex.submit(_mode_job, seq_dir, str(out_root / f"mode_{mode}_{rerun}"), mode,
                                                rerun).result())
        best = {m: max(v, key=lambda r: r["fps"]) for m, v in runs.items()}
        res[rerun] = {
            "sequential": {k: v for k, v in best["sequential"].items() if k != "trajectory"},
            "pipelined": {k: v for k, v in best["pipelined"].items() if k != "trajectory"},
            "speedup": best["pipelined"]["fps"] / best["sequential"]["fps"],
            "identical": all(r["trajectory"] == runs["sequential"][0]["trajectory"]
                             for v in runs.values() for r in v),
        }
    with ProcessPoolExecutor(max_workers=1) as ex:
        res["chaining_fps"] = ex.submit(_chaining_fps, seq_dir).result()
    return res


def bench_rerun(cache: Path, out_root: Path, repeats: int = 3) -> dict:
    """Cost of the Rerun recording (image on every frame, JPEG) on the 30 s loop: whole jobs with the
    recording off and on, alternated, each in a fresh process; the fastest of ``repeats`` counts
    (the others are slowed by whatever else runs on the machine)."""
    case = synthetic_cases(30.0)[0]
    seq_dir = str(ensure_rendered(case, cache))
    runs: dict[str, list[dict]] = {"off": [], "on": []}
    for _ in range(repeats):
        for key in ("off", "on"):
            with ProcessPoolExecutor(max_workers=1) as ex:
                runs[key].append(ex.submit(_rerun_job, seq_dir, str(out_root / f"rerun_{key}"), key == "on").result())
    res: dict = {k: min(v, key=lambda r: r["wall_s"]) for k, v in runs.items()}
    off, on = res["off"], res["on"]
    res["overhead_pct"] = 100.0 * (on["wall_s"] / off["wall_s"] - 1.0)
    res["cpu_overhead_pct"] = 100.0 * (on["cpu_s"] / off["cpu_s"] - 1.0)
    # The logger's own time in the run's thread, as a share of the job without recording.
    res["viewer_busy_pct"] = 100.0 * min(r["viewer_busy_s"] for r in runs["on"]) / off["wall_s"]
    res["kb_per_frame"] = 1000.0 * on["size_mb"] / on["frames"]
    return res


def _run_bag_peak_rss(bag: str, out: str) -> dict:
    import logging

    logging.basicConfig(level=logging.ERROR)
    from ..runtime.job import run_job

    cfg = config_from_dict({"sequence": bag, "dataset": "rosbag", "output": out, "progress": False,
                            "viz": {"rerun": "off"}})
    rep = run_job(cfg)
    return {"frames": rep.result.n_frames, "keyframes": rep.result.n_keyframes, "fps": rep.result.fps,
            "peak_rss_mb": peak_rss_mb()}


def bench_bag(cache: Path, out_root: Path, factor: int = 10, storage: str = "mcap") -> dict:
    """Peak RSS of a run on a ROS bag of a rendered loop and on a bag ``factor`` times as large.

    The large bag drives the same loop forward, back, forward, ... (images, wheel odometry and
    ground truth follow the same time map). Frames are streamed from the bag, so peak memory
    should not grow with its size. Each run is its own process; the bags are written once.
    """
    import multiprocessing

    from ..synth.bagwriter import BagSpec, write_bag
    from ..synth.generate import SynthSpec, generate_sequence
    from ..synth.paths import PathKind

    d = cache / "bag_loop"
    if not (d / "synth.json").is_file():
        generate_sequence(d, SynthSpec(path=PathKind.LOOP, duration_s=15.0, seed=45))
    res: dict = {}
    for name, repeat in (("small", 1), (f"x{factor}", factor)):
        bag = cache / f"bag_loop_{storage}_{repeat}" / ("bag.bag" if storage == "ros1" else "bag")
        if not bag.exists():
            bag.parent.mkdir(parents=True, exist_ok=True)
            write_bag(d, bag, BagSpec(storage=storage, groundtruth="pose", repeat=repeat))
        files = [bag] if bag.is_file() else [p for p in bag.iterdir() if p.is_file()]
        # A fresh interpreter (spawn): a forked worker would start with this process's pages.
        with ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn")) as ex:
            row = ex.submit(_run_bag_peak_rss, str(bag), str(out_root / f"bag_{name}")).result()
        row["bag_mb"] = sum(p.stat().st_size for p in files) / 2**20
        res[name] = row
    res["growth_pct"] = 100.0 * (res[f"x{factor}"]["peak_rss_mb"] / res["small"]["peak_rss_mb"] - 1.0)
    return res
