"""The README's two set-up commands are the ones CI and users run; its Python example runs as
written; every CLI option is documented in docs/CLI.md."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
README = (REPO / "README.md").read_text()
CLI_DOC = (REPO / "docs" / "CLI.md").read_text()


def setup_commands() -> list[str]:
    section = README.split("## Set up and run", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```bash\n(.*?)```", section, re.S)
    return [line for block in blocks for line in block.splitlines() if line and not line.startswith("#")]


def test_exactly_two_setup_commands():
    assert len(setup_commands()) == 2


def test_ci_runs_the_readme_test_command():
    test_command = setup_commands()[1]
    assert "pytest" in test_command
    assert test_command in (REPO / ".ci" / "run").read_text().splitlines()


def test_main_job_uses_files_shipped_in_examples():
    main_job = setup_commands()[0]
    for path in re.findall(r"examples/\S+", main_job):
        assert (REPO / path).is_file(), path
    assert (REPO / "examples" / "LICENSES.md").is_file()


@pytest.mark.parametrize("command", ["relight", "shade", "eval", "info"])
def test_every_cli_option_is_documented(command):
    from relightcli import cli

    parser = {"relight": cli.relight_parser, "shade": cli.shade_parser, "eval": cli.eval_parser,
              "info": cli.info_parser}[command]()
    for action in parser._actions:
        for flag in action.option_strings:
            if flag.startswith("--") and flag not in ("--help", "--version"):
                assert f"`{flag}" in CLI_DOC, f"{command}: {flag} is not documented in docs/CLI.md"


def test_the_readme_is_a_users_page():
    assert len(README.splitlines()) <= 220
    assert "(docs/CLI.md)" in README and "(docs/RESULTS.md)" in README
    assert (REPO / "docs" / "CLI.md").is_file() and (REPO / "docs" / "RESULTS.md").is_file()


def test_the_python_example_runs_as_written(tmp_path):
    """The README's ```python block, run as a script in a folder laid out like the repository's
    root (its examples/), with the installed relightcli."""
    blocks = re.findall(r"```python\n(.*?)```", README, re.S)
    assert len(blocks) == 1
    shutil.copytree(REPO / "examples", tmp_path / "examples")
    (tmp_path / "example.py").write_text(blocks[0])
    run = subprocess.run([sys.executable, "example.py"], cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    written = sorted(p.name for p in (tmp_path / "out").iterdir())
    assert written == ["skier.png", "skier_albedo.png", "skier_kloofendal_overcast.png", "skier_noon_grass.png",
                       "skier_shading.exr"]
    assert "(425, 640, 3)" in run.stdout
