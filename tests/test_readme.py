"""The README's code runs as written (issue #28): every ```bash and ```python block, section by section.

The blocks of one README section run in order, in one fresh working folder per section, as a user
following that section would (a ```bash block as one ``bash -e`` script, a ```python block as a
script), each with a time-out. The folder has ``../shared`` linked to the repository's sibling
``shared/`` (the KITTI excerpts) and ``configs/`` linked to the repository's, so relative paths in
the README mean what they mean from the repository's root. A section that names a ``../shared/data``
path that is absent skips with that reason.

Commands that cannot run in a test are listed in ``NOT_RUN`` with the reason; each entry must still
be a command line of the README (so the list cannot go stale), and the rest of its block runs.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
SHARED = REPO.parent / "shared"

# Command lines of the README that the tests do not run, and why (matched without their `# comment`).
NOT_RUN = {
    "python3 -m venv .venv && . .venv/bin/activate && pip install -e . && python -m windowvo.run":
        "makes a venv and installs from the network: CI runs it (.ci/run), and "
        "tests/test_pipeline.py::test_default_run_from_the_command_line runs `python -m windowvo.run`",
    'python3 -m venv .venv && . .venv/bin/activate && pip install -e ".[test]" && python -m pytest -q -n 2':
        "the test suite itself: CI runs exactly this command (.ci/run)",
    'python -m pytest -q -n 2 -m "not slow"':
        "the test suite itself (a subset of it)",
    "python -m windowvo.run quick.yaml viz.rerun=spawn":
        "opens a native viewer window: needs a display",
    "python -m windowvo.view out/quick":
        "opens a native viewer window: needs a display (tests/test_rerun*.py read recordings instead)",
    "python -m windowvo.batch batch.yaml --executor ray --address ray://head:10001":
        "needs a Ray cluster at that address (tests/test_batch.py runs the Ray executor locally)",
}
# Docs the README links to that other issue-#28 work writes on its own branch: absent here until merged.
# Each must really be absent (so an entry cannot outlive its merge); delete it once the file lands.
PENDING_DOCS: set[str] = set()  # docs linked before they land (none now)
LANGUAGES = {"bash": "run", "python": "run", "yaml": "parsed", "text": "shown"}
TIMEOUT_S = 600  # per block; generous because the machine's two cores are shared
HEADING = re.compile(r"^(#{2,3}) (.+)$")
FENCE = re.compile(r"^```(\S*)\s*$")


@dataclass(frozen=True)
class Block:
    section: str  # the nearest ## or ### heading above the block
    language: str
    code: str
    line: int  # README line of the opening fence


def readme_blocks(text: str) -> list[Block]:
    blocks: list[Block] = []
    section, lang, start, body = "", None, 0, []
    for n, line in enumerate(text.splitlines(), 1):
        fence = FENCE.match(line)
        if lang is None:
            heading = HEADING.match(line)
            if heading:
                section = heading.group(2).strip()
            elif fence:
                lang, start, body = fence.group(1), n, []
        elif fence and not fence.group(1):
            blocks.append(Block(section, lang, "\n".join(body) + "\n", start))
            lang = None
        else:
            body.append(line)
    assert lang is None, f"README.md:{start}: code block never closed"
    return blocks


BLOCKS = readme_blocks(README.read_text())
RUNNABLE = [b for b in BLOCKS if b.language in ("bash", "python")]
SECTIONS = list(dict.fromkeys(b.section for b in RUNNABLE))


def command_of(line: str) -> str:
    """A bash line without its `# comment` (none of the README's commands quote a '#')."""
    return "" if line.lstrip().startswith("#") else line.split(" #", 1)[0].strip()


def bash_lines(block: Block) -> list[str]:
    return [command_of(line) for line in block.code.splitlines()]


def runnable_script(block: Block) -> str:
    out = []
    for line in block.code.splitlines():
        reason = NOT_RUN.get(command_of(line))
        out.append(f": 'not run in tests: {reason}'" if reason else line)
    return "\n".join(out) + "\n"


def work_folder(root: Path) -> tuple[Path, dict[str, str]]:
    """A fresh folder that looks like the repository's root to the README's relative paths, and an
    environment whose `python` is this interpreter importing this checkout."""
    work = root / "repo"
    work.mkdir()
    (work / "configs").symlink_to(REPO / "configs")
    if SHARED.is_dir():
        (root / "shared").symlink_to(SHARED)
    bin_dir = root / "bin"
    bin_dir.mkdir()
    shim = bin_dir / "python"  # a wrapper, not a link: a link outside the venv would lose the venv
    shim.write_text(f'#!/bin/sh\nexec "{sys.executable}" "$@"\n')
    shim.chmod(0o755)
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    env.update(PYTHONPATH=str(REPO), PATH=f"{bin_dir}{os.pathsep}{env.get('PATH', '')}", MPLBACKEND="Agg",
               PYTHONUNBUFFERED="1")
    return work, env


def missing_shared_data(code: str) -> list[str]:
    names = set(re.findall(r"\.\./shared/data/([\w.+-]+)", code))
    return sorted(n for n in names if not (SHARED / "data" / n).exists())


def run_block(block: Block, work: Path, env: dict[str, str]) -> subprocess.CompletedProcess:
    if block.language == "bash":
        cmd = ["bash", "-e", "-o", "pipefail", "-c", runnable_script(block)]
    else:
        script = work / f"readme_block_{block.line}.py"
        script.write_text(block.code)
        cmd = [sys.executable, script.name]
    return subprocess.run(cmd, cwd=work, env=env, capture_output=True, text=True, timeout=TIMEOUT_S)


# ---------------------------------------------------------------------------------------------- static checks


def test_every_code_block_is_of_a_known_kind():
    """A command labelled ```sh or ```console would escape the runs below: only known kinds are allowed."""
    unknown = [(b.line, b.language) for b in BLOCKS if b.language not in LANGUAGES]
    assert unknown == [], f"README.md code blocks of an unknown kind (line, language): {unknown}; use {LANGUAGES}"
    assert len(RUNNABLE) >= 10, "the README lost its runnable examples"


def test_yaml_blocks_parse():
    for b in BLOCKS:
        if b.language == "yaml":
            assert isinstance(yaml.safe_load(b.code), dict), f"README.md:{b.line}: not a YAML mapping"


def test_every_not_run_entry_is_a_readme_command():
    """The allow-list cannot go stale: each entry is still a command line of a ```bash block."""
    lines = {line for b in BLOCKS if b.language == "bash" for line in bash_lines(b)}
    stale = [cmd for cmd in NOT_RUN if cmd not in lines]
    assert stale == [], f"NOT_RUN names commands the README no longer has: {stale}"


def test_the_two_set_up_commands_are_in_the_readme():
    setup = next(b for b in BLOCKS if b.section.startswith("Set-up"))
    assert [cmd for cmd in bash_lines(setup) if cmd] == list(NOT_RUN)[:2]


def test_length_and_local_links():
    """A user guide of at most 400 lines, whose links to docs/ and pictures point at files that exist."""
    text = README.read_text()
    assert len(text.splitlines()) <= 400
    targets = re.findall(r"\]\(([^)#\s]*)(?:#([\w-]+))?\)", text)
    assert targets, "no links found"
    for path, anchor in targets:
        if "://" in path:
            continue
        target = REPO / path if path else README
        if path in PENDING_DOCS:
            assert not target.exists(), f"{path} has landed: remove it from PENDING_DOCS"
            continue
        assert target.exists(), f"README links to a missing file: {path}"
        if anchor and target.suffix == ".md":
            assert anchor in markdown_anchors(target.read_text()), f"no heading for #{anchor} in {path}"


def markdown_anchors(text: str) -> set[str]:
    """GitHub's heading anchors: lower case, punctuation dropped, spaces to hyphens."""
    heads = re.findall(r"^#+ (.+)$", text, flags=re.MULTILINE)
    return {re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-") for h in heads}


def test_block_parser_on_a_constructed_readme():
    text = "## A\n```bash\necho 1  # one\n```\n### B\n```python\nprint(2)\n```\n```text\nout\n```\n"
    blocks = readme_blocks(text)
    assert [(b.section, b.language, b.code, b.line) for b in blocks] == [
        ("A", "bash", "echo 1  # one\n", 2), ("B", "python", "print(2)\n", 6), ("B", "text", "out\n", 9)]
    assert bash_lines(blocks[0]) == ["echo 1"]


# ---------------------------------------------------------------------------------------------- the runs


@pytest.mark.slow
@pytest.mark.parametrize("section", SECTIONS)
def test_readme_section_runs_as_written(section, tmp_path):
    blocks = [b for b in RUNNABLE if b.section == section]
    absent = missing_shared_data("".join(b.code for b in blocks))
    if absent:
        pytest.skip(f"README section '{section}' needs ../shared/data/{absent[0]}, which is absent")
    commands = [c for b in blocks if b.language == "bash" for c in bash_lines(b) if c]
    if commands and all(c in NOT_RUN for c in commands) and all(b.language == "bash" for b in blocks):
        pytest.skip(f"README section '{section}': every command is in NOT_RUN ({NOT_RUN[commands[0]]})")
    work, env = work_folder(tmp_path)
    for b in blocks:
        r = run_block(b, work, env)
        assert r.returncode == 0, f"README.md:{b.line} ({section}) failed, exit {r.returncode}:\n{r.stdout}\n{r.stderr}"
        assert "Traceback" not in r.stderr, f"README.md:{b.line} ({section}):\n{r.stderr}"
