import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from pydantic import Field, create_model

from windowvo.config import RerunMode, TrackerKind, config_from_dict, load_config
from windowvo.errors import ConfigError
from windowvo.tools import config_doc


def write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "cfg.yaml"
    p.write_text(text)
    return p


def test_minimal_config_and_relative_paths(tmp_path):
    cfg = load_config(write(tmp_path, "sequence: seq\noutput: out\n"))
    assert cfg.sequence == (tmp_path / "seq").resolve()
    assert cfg.output == (tmp_path / "out").resolve()
    assert cfg.frontend.max_features == 200
    assert cfg.viz.rerun is RerunMode.SAVE


def test_overrides_are_typed(tmp_path):
    cfg = load_config(write(tmp_path, "sequence: s\noutput: o\n"),
                      ["frontend.max_features=300", "frontend.tracker=orb", "viz.rerun=off", "backend.planar_prior.enabled=false"])
    assert cfg.frontend.max_features == 300
    assert cfg.frontend.tracker is TrackerKind.ORB
    assert cfg.viz.rerun is RerunMode.OFF
    assert cfg.backend.planar_prior.enabled is False


@pytest.mark.parametrize(
    "text,needle",
    [
        ("sequence: s\noutput: o\nfrontend:\n  max_feature: 3\n", "'frontend.max_feature': unknown key"),
        ("sequence: s\noutput: o\nfrontend:\n  max_features: lots\n", "'frontend.max_features'"),
        ("sequence: s\noutput: o\nbackend:\n  window_keyframes: 0\n", "'backend.window_keyframes'"),
        ("sequence: s\noutput: o\nbackend:\n  pixel_sigma: -1\n", "'backend.pixel_sigma'"),
        ("output: o\n", "'sequence': required key is missing"),
        ("sequence: s\noutput: o\ndataset: hdf5\n", "'dataset'"),
        ("- a\n- b\n", "mapping"),
        ("sequence: [unclosed\n", "not valid YAML"),
        ("sequence: s\noutput: o\nbackend:\n  ground:\n    mount_calibration: maybe\n",
         "'backend.ground.mount_calibration'"),
    ],
)
def test_bad_config_gives_one_clear_line(tmp_path, text, needle):
    with pytest.raises(ConfigError) as exc:
        load_config(write(tmp_path, text))
    msg = str(exc.value)
    assert needle in msg
    assert "\n" not in msg


@pytest.mark.parametrize("value,mode", [("true", "on"), ("false", "off"), ("auto", "auto"), ("off", "off")])
def test_mount_calibration_accepts_the_old_booleans(tmp_path, value, mode):
    cfg = load_config(write(tmp_path, f"sequence: s\noutput: o\nbackend:\n  ground:\n    mount_calibration: {value}\n"))
    assert cfg.backend.ground.mount_calibration.value == mode


def test_bad_override(tmp_path):
    with pytest.raises(ConfigError, match="key=value"):
        load_config(write(tmp_path, "sequence: s\noutput: o\n"), ["frontend.max_features"])
    with pytest.raises(ConfigError, match="unknown key"):
        load_config(write(tmp_path, "sequence: s\noutput: o\n"), ["frontend.nope=1"])


def test_missing_config_file(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "nope.yaml")


EXAMPLE = Path(__file__).resolve().parents[1] / "configs" / "example.yaml"


def test_example_config_is_valid():
    cfg = load_config(EXAMPLE)
    assert cfg.frontend.tracker is TrackerKind.KLT and cfg.backend.window_keyframes == 20
    # it must not pin the prior on: the tum and euroc layouts turn it off unless it is set
    assert "enabled" not in cfg.backend.planar_prior.model_fields_set


def test_example_config_shows_the_defaults():
    """The example says every key in it shows its default: check each one against the models."""
    example = yaml.safe_load(EXAMPLE.read_text())
    defaults = config_from_dict({"sequence": "s", "output": "o"}).to_yaml_dict()

    def walk(node: dict, ref: dict, prefix: str) -> None:
        for key, value in node.items():
            where = prefix + key
            assert key in ref, f"{where}: not a config key"
            if isinstance(value, dict):
                walk(value, ref[key], where + ".")
            elif where not in ("sequence", "output"):
                assert value == ref[key], f"{where}: example says {value!r}, the default is {ref[key]!r}"

    walk(example, defaults, "")


def _run_cli(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "windowvo.run", *args], capture_output=True, text=True, timeout=300,
                          cwd=cwd)


@pytest.mark.parametrize("where", ["output_is_file", "parent_is_file"])
def test_output_that_is_a_file_is_one_line_and_exit_2(tmp_path, where):
    """An `output:` that is an existing file (or lies under one) stops before any work, with one line."""
    blocker = tmp_path / "taken.txt"
    blocker.write_text("not a folder\n")
    out = blocker if where == "output_is_file" else blocker / "out"
    cfg = write(tmp_path, f"sequence: {tmp_path / 'seq'}\noutput: {out}\nprogress: false\nviz:\n  rerun: 'off'\n")
    r = _run_cli(str(cfg))
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("windowvo: error: output '")
    assert ("is an existing file" if where == "output_is_file" else "is a file, not a folder") in lines[0]
    assert blocker.read_text() == "not a folder\n"


# ---------------------------------------------------------------------------- config reference

README = Path(__file__).resolve().parents[1] / "docs" / "config.md"  # the generated config reference (moved out of README.md, issue #28)


def test_every_config_key_has_a_description():
    missing = config_doc.missing_descriptions()
    assert missing == [], f"add Field(..., description=...) in windowvo/config.py for: {missing}"


def test_readme_config_reference_is_the_generated_one():
    """The README's reference is exactly what the config models generate: a key added, removed or
    re-described without regenerating fails here."""
    in_readme = config_doc.reference_in(README.read_text())
    assert in_readme == config_doc.generate_reference(), f"stale config reference: run {config_doc.REGENERATE}"
    for k in config_doc.iter_keys():
        assert f"`{k.key}`" in in_readme


def test_reference_generator_catches_undescribed_keys():
    inner = create_model("Inner", documented=(int, Field(1, description="has one")), bare=(int, 2))
    outer = create_model("Outer", sub=(inner, Field(inner(), description="a section")),
                         top=(float, Field(1.5, description="a number")), loose=(inner, inner()))
    assert config_doc.missing_descriptions(outer) == ["sub.bare", "loose", "loose.bare"]
    with pytest.raises(ConfigError, match=r"sub\.bare"):
        config_doc.generate_reference(outer)
    keys = {k.key: k for k in config_doc.iter_keys(outer)}
    assert keys["top"].default == "`1.5`" and keys["sub"].is_section and keys["sub.documented"].type == "int"


def test_reference_command_line_check_and_write(tmp_path):
    doc = tmp_path / "DOC.md"
    doc.write_text(f"intro\n{config_doc.START}\n| old | table |\n{config_doc.END}\noutro\n")
    run = [sys.executable, "-m", "windowvo.config_doc"]
    stale = subprocess.run([*run, "--check", str(doc)], capture_output=True, text=True, timeout=120)
    assert stale.returncode == 1 and "stale config reference" in stale.stderr
    assert subprocess.run([*run, "--write", str(doc)], capture_output=True, text=True, timeout=120).returncode == 0
    text = doc.read_text()
    assert text.startswith("intro\n") and text.endswith(f"{config_doc.END}\noutro\n")
    assert config_doc.reference_in(text) == config_doc.generate_reference()
    assert subprocess.run([*run, "--check", str(doc)], capture_output=True, text=True, timeout=120).returncode == 0
    (tmp_path / "none.md").write_text("no markers\n")
    bad = subprocess.run([*run, "--write", str(tmp_path / "none.md")], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "Traceback" not in bad.stderr and "config-reference:start" in bad.stderr
