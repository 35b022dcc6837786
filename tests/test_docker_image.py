"""The Dockerfile, its build context and the maintainer's engine check, read as text (issue 51;
no Docker engine runs in CI: docker/check.sh is the check against a real one)."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCKERFILE = (REPO / "Dockerfile").read_text()
README = (REPO / "README.md").read_text()
CHECK = REPO / "docker" / "check.sh"


def instructions(keyword: str) -> list[str]:
    """The Dockerfile's KEYWORD lines (continuations joined), without the keyword."""
    joined = re.sub(r"\\\n", " ", DOCKERFILE)
    return [line[len(keyword):].strip() for line in joined.splitlines() if line.startswith(keyword + " ")]


def readme_docker_run() -> str:
    lines = [line for line in README.splitlines() if line.startswith("docker run ")]
    assert len(lines) == 1, lines
    return lines[0]


def test_base_image_is_pinned_by_digest_with_an_update_procedure():
    (base,) = [arg for arg in instructions("ARG") if arg.startswith("BASE_IMAGE=")]
    assert re.fullmatch(r"BASE_IMAGE=python:3\.11-slim-bookworm@sha256:[0-9a-f]{64}", base)
    assert instructions("FROM") == ["${BASE_IMAGE} AS build", "${BASE_IMAGE} AS runtime"]
    header = DOCKERFILE.split("ARG BASE_IMAGE")[0]
    assert "To update:" in header and "not pulled or checked" in header  # says what was verified


def test_the_build_context_holds_what_the_dockerfile_copies_and_nothing_else():
    rules = [line for line in (REPO / ".dockerignore").read_text().splitlines()
             if line and not line.startswith("#")]
    assert rules[0] == "*"
    allowed = {rule[1:] for rule in rules if rule.startswith("!")}
    copied = {source for copy in instructions("COPY") if not copy.startswith("--from")
              for source in copy.split()[:-1]}
    assert copied == allowed


def test_tini_is_pid_1_and_starts_the_entrypoint_isolated():
    assert "apt-get install -y --no-install-recommends tini" in DOCKERFILE
    (entry,) = instructions("ENTRYPOINT")
    assert entry.startswith('["/usr/bin/tini", "--", "/opt/venv/bin/python", "-I", ')
    target = re.search(r'"(/[^"]+entrypoint\.py)"', entry).group(1)
    assert f"COPY docker/entrypoint.py {target}" in DOCKERFILE


def test_the_readme_command_needs_no_user_flag():
    assert "--user" not in readme_docker_run() and "--platform linux/amd64" in README


def test_the_engine_check_runs_the_readme_command_word_for_word():
    command = readme_docker_run().replace(" relightcli ", ' "$IMAGE" ')
    assert command in CHECK.read_text()


@pytest.mark.skipif(shutil.which("bash") is None, reason="needs bash")
def test_the_engine_check_is_an_executable_bash_script():
    assert os.access(CHECK, os.X_OK)
    subprocess.run(["bash", "-n", str(CHECK)], check=True)
