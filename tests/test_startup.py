"""What a run's main process loads before its first frame: GTSAM lives in the back-end process, evo (and scipy
under it) only in the evaluation after the run. Each is 0.1-0.4 s of start-up (docs/performance.md)."""

from __future__ import annotations

import subprocess
import sys

HEAVY = ("gtsam", "evo", "scipy")


def _loaded_after(code: str) -> list[str]:
    probe = f"import sys; {code}; print(' '.join(m for m in {HEAVY!r} if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, check=True)
    return out.stdout.split()


def test_the_job_module_loads_no_back_end_and_no_evaluator():
    assert _loaded_after("import windowvo.runtime.job, windowvo.runtime.pipeline, windowvo.runtime.outputs") == []


def test_a_remote_back_end_odometry_loads_no_gtsam():
    """The pipelined run's main process builds an Odometry whose back end runs elsewhere."""
    code = ("from windowvo.runtime.stream import Odometry; from windowvo.camera import CameraModel; "
            "Odometry(CameraModel(64, 48, 50.0, 50.0, 32.0, 24.0), remote_backend=True)")
    assert "gtsam" not in _loaded_after(code)


def test_a_local_back_end_still_loads_it():
    """The check above can fail: the same Odometry with its own back end does load GTSAM."""
    code = ("from windowvo.runtime.stream import Odometry; from windowvo.camera import CameraModel; "
            "Odometry(CameraModel(64, 48, 50.0, 50.0, 32.0, 24.0))")
    assert "gtsam" in _loaded_after(code)


def test_the_back_end_loads_no_scipy():
    """The back end's chi-square quantiles are computed without scipy (0.18 s of every back end's start)."""
    assert _loaded_after("import windowvo.backend.smoother") == ["gtsam"]


RECORD = ("import numpy as np, rerun as rr; rec = rr.RecordingStream('t'); rec.save({path!r}); "
          "rec.log('a', rr.Points2D(np.zeros((3, 2)))); rec.flush()")


def test_a_command_line_run_records_without_pandas(tmp_path):
    """pyarrow under rerun imports pandas at the first conversion (0.3 s); the command-line run hides it."""
    code = ("from windowvo.cli.hidden_modules import pandas_hidden\nwith pandas_hidden():\n    "
            + RECORD.format(path=str(tmp_path / "a.rrd")) + "\n    assert 'pandas' not in sys.modules")
    probe = f"import sys\n{code}\nimport pandas\nprint('pandas' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.split() == ["True"]  # importable again once the run is over
    assert (tmp_path / "a.rrd").stat().st_size > 0


def test_recording_loads_pandas_when_not_hidden(tmp_path):
    """The check above can fail: the same recording, pandas not hidden, loads it."""
    probe = "import sys; " + RECORD.format(path=str(tmp_path / "b.rrd")) + "; print('pandas' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.split() == ["True"]


def test_the_command_line_entry_hides_pandas():
    """``python -m windowvo.run`` runs inside ``pandas_hidden``, and leaves no finder behind."""
    probe = ("import sys; import windowvo.cli.run as r; seen = []\n"
             "def fake(argv):\n    seen.append('pandas' not in sys.modules and any(type(f).__name__ == '_Hide' "
             "for f in sys.meta_path)); return 0\n"
             "r._main = fake; r.main([]); print(seen[0], any(type(f).__name__ == '_Hide' for f in sys.meta_path))")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.split() == ["True", "False"]
