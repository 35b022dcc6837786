"""The README's two set-up commands are the ones CI and users run."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
README = (REPO / "README.md").read_text()


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
                assert f"`{flag}" in README, f"{command}: {flag} is not documented in README.md"
