"""Inference needs no torch: a fresh virtual environment built from the runtime requirements
alone (what the Dockerfile installs) runs `relight` and imports every relightcli module.
The Dockerfile is checked by construction, since no Docker engine runs here."""

from __future__ import annotations

import json
import os
import pkgutil
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCKERFILE = (REPO / "Dockerfile").read_text()

# Packages every python:3.11-slim-bookworm image has (Debian essentials + Python's own needs).
BASE_IMAGE_PACKAGES = {"libc6", "libgcc-s1", "libstdc++6", "zlib1g", "libcom-err2", "libgpg-error0"}

IMPORT_EVERYTHING = """
import importlib, pkgutil, sys
import relightcli
names = [m.name for m in pkgutil.walk_packages(relightcli.__path__, 'relightcli.')
         if not m.name.endswith('__main__')]  # __main__ runs the CLI
for name in names:
    importlib.import_module(name)
torch = [m for m in sys.modules if m == 'torch' or m.startswith('torch.')]
print(len(names), 'modules', 'torch' if torch else 'no-torch')
"""

@pytest.fixture(scope="module")
def runtime_venv(tmp_path_factory):
    """A fresh venv holding the relightcli wheel built from this checkout, installed with
    `pip install -c requirements.lock WHEEL` and nothing else (no system packages, no torch)."""
    if shutil.which("pip") is None and not (Path(sys.executable).parent / "pip").exists():
        pytest.skip("pip is not available")
    root = tmp_path_factory.mktemp("runtime")
    venv = root / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    python = venv / "bin" / "python"
    src = root / "src"  # a copy, so the build leaves nothing in the checkout
    skipped = shutil.ignore_patterns(".git", ".venv*", "*.egg-info", "build", "dist", "__pycache__", "examples",
                                     "bench", "export", "tests")

    def ignore(folder, names):  # and the checkout's own data/ (gitignored: datasets being written)
        return skipped(folder, names) | ({"data"} if Path(folder) == REPO else set())

    shutil.copytree(REPO, src, ignore=ignore)
    pip = [str(python), "-m", "pip", "--disable-pip-version-check", "--quiet"]
    _run_or_fail(pip + ["wheel", "--no-deps", "-w", str(root / "dist"), str(src)])
    wheel = next((root / "dist").glob("relightcli-*.whl"))
    _run_or_fail(pip + ["install", "-c", str(src / "requirements.lock"), str(wheel)])
    shutil.rmtree(src)  # nothing of the checkout is left to find the models in
    return venv


def _run_or_fail(command: list[str]) -> None:
    result = subprocess.run(command, capture_output=True, text=True, timeout=900)
    if result.returncode != 0:
        pytest.fail(f"{' '.join(command)} failed:\n{result.stdout[-3000:]}\n{result.stderr[-3000:]}")


def run_in(venv: Path, *args: str, cwd: Path | None = None, env: dict | None = None) -> subprocess.CompletedProcess:
    """Run a command of the venv with no RELIGHT_MODELS_DIR (unless `env` sets it)."""
    clean = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "RELIGHT_MODELS_DIR")}
    return subprocess.run(list(args), capture_output=True, text=True, cwd=cwd or venv,
                          env={**clean, **(env or {})}, timeout=300)


def test_runtime_venv_has_no_torch(runtime_venv):
    out = run_in(runtime_venv, str(runtime_venv / "bin" / "python"), "-c",
                 "import importlib.util as u; print(u.find_spec('torch') is None)")
    assert out.stdout.strip() == "True", out.stderr


def test_runtime_venv_relight_help(runtime_venv):
    help_out = run_in(runtime_venv, str(runtime_venv / "bin" / "relight"), "--help")
    assert help_out.returncode == 0, help_out.stderr
    assert "--hdr" in help_out.stdout


def test_installed_wheel_carries_its_models_checked_by_sha256(runtime_venv, tmp_path):
    info = run_in(runtime_venv, str(runtime_venv / "bin" / "relight"), "info", "--json", cwd=tmp_path)
    assert info.returncode == 0, info.stderr
    report = json.loads(info.stdout)
    assert "CPUExecutionProvider" in report["providers"]
    site = next((runtime_venv / "lib").glob("python3*/site-packages"))
    assert Path(report["models_dir"]) == site / "relightcli" / "models"
    shipped = json.loads((REPO / "models" / "manifest.json").read_text())["models"]
    assert sorted(m["name"] for m in report["models"]) == sorted(shipped)
    assert all(m["present"] and m["sha256_ok"] for m in report["models"]), report["models"]


def test_installed_wheel_relights_the_example_from_another_directory(runtime_venv, tmp_path):
    for name in ("skier.jpg", "skier_mask.png", "noon_grass.hdr"):
        shutil.copy(REPO / "examples" / name, tmp_path / name)
    out = run_in(runtime_venv, str(runtime_venv / "bin" / "relight"), "skier.jpg", "--mask", "skier_mask.png",
                 "--hdr", "noon_grass.hdr", "-o", "out/skier.png", "--outputs", "relit,albedo",
                 "--resolution", "256", cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    relit = (tmp_path / "out" / "skier.png").read_bytes()
    assert relit.startswith(b"\x89PNG") and (tmp_path / "out" / "skier_albedo.png").is_file()


def test_relight_models_dir_still_overrides_the_packaged_models(runtime_venv, tmp_path):
    empty = tmp_path / "no-models"
    empty.mkdir()
    info = run_in(runtime_venv, str(runtime_venv / "bin" / "relight"), "info", cwd=tmp_path,
                  env={"RELIGHT_MODELS_DIR": str(empty)})
    assert info.returncode == 3
    assert str(empty / "manifest.json") in info.stderr and "RELIGHT_MODELS_DIR" in info.stderr


def test_installed_wheel_holds_every_module_and_imports_them_without_torch(runtime_venv):
    out = run_in(runtime_venv, str(runtime_venv / "bin" / "python"), "-c", IMPORT_EVERYTHING)
    assert out.returncode == 0, out.stderr
    count, _, verdict = out.stdout.split()
    in_source = [m for m in pkgutil.walk_packages([str(REPO / "relightcli")], "relightcli.")
                 if not m.name.endswith("__main__")]
    assert int(count) == len(in_source) and verdict == "no-torch", out.stdout


def dockerfile_apt_packages() -> set[str]:
    block = re.search(r"apt-get install[^\n]*\\\n((?:.*\\\n)+)", DOCKERFILE)
    if block is None:
        return set()
    return {word for word in block.group(1).replace("\\", " ").split() if re.fullmatch(r"lib[\w.+-]+", word)}


def test_dockerfile_installs_every_system_library_the_wheels_load(runtime_venv):
    if shutil.which("dpkg") is None or shutil.which("ldd") is None:
        pytest.skip("needs Debian's dpkg and ldd (the image is Debian bookworm too)")
    site = next((runtime_venv / "lib").glob("python3*/site-packages"))
    system_libs = set()
    for so in site.rglob("*.so*"):
        out = subprocess.run(["ldd", str(so)], capture_output=True, text=True)
        for line in out.stdout.splitlines():
            match = re.search(r"=> (/\S+)", line)
            if match and str(site) not in match.group(1):
                system_libs.add(os.path.realpath(match.group(1)))
    packages = set()
    for lib in sorted(system_libs):
        owner = subprocess.run(["dpkg", "-S", lib], capture_output=True, text=True)
        if owner.returncode != 0:  # usr-merge: dpkg may know the /lib spelling
            owner = subprocess.run(["dpkg", "-S", lib.replace("/usr/lib/", "/lib/")], capture_output=True, text=True)
        if owner.returncode == 0:
            packages.add(owner.stdout.split(":")[0])
    assert "libc6" in packages  # the scan found the wheels' libraries at all
    missing = packages - BASE_IMAGE_PACKAGES - dockerfile_apt_packages()
    assert not missing, f"the Dockerfile's runtime stage must apt-get install {sorted(missing)}"


def test_dockerfile_shape():
    # multi-stage, same base: python:3.11-slim-bookworm pinned by digest (tests/test_docker_image.py)
    assert re.search(r"^ARG BASE_IMAGE=python:3\.11-slim-bookworm@sha256:", DOCKERFILE, re.M)
    assert DOCKERFILE.count("FROM ${BASE_IMAGE}") == 2
    assert "torch" not in re.sub(r"#.*", "", DOCKERFILE).replace("find_spec('torch')", "")
    assert "-c requirements.lock ." in DOCKERFILE  # the same pins as the runtime test
    # relight runs as the output's owner, never as root unless the caller is (docker/entrypoint.py)
    assert not re.search(r"^USER root", DOCKERFILE, re.M)
    assert re.search(r'^ENTRYPOINT \["/usr/bin/tini", "--", .*entrypoint\.py"\]', DOCKERFILE, re.M)
    # The models reach the image inside the wheel, not through an environment variable
    assert "COPY models ./models" in DOCKERFILE and "RELIGHT_MODELS_DIR" not in DOCKERFILE
    assert "relight info" in DOCKERFILE  # the build fails if the installed models are not found
    assert "!export" not in (REPO / ".dockerignore").read_text().split()


def test_runtime_dependencies_exclude_torch():
    import tomllib

    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    runtime = " ".join(project["dependencies"]).lower()
    assert "torch" not in runtime and "onnx>=" not in runtime
    pinned = {line.split("==")[0].lower() for line in (REPO / "requirements.lock").read_text().splitlines()
              if "==" in line and not line.startswith("#")}
    for requirement in project["dependencies"]:
        name = re.split(r"[<>=\[ ]", requirement)[0].lower()
        assert name in pinned, f"{name} is a runtime dependency missing from requirements.lock"
