"""Packaging: kernels/ installs as holowarp.kernels only; CI runs the README's test command."""

from __future__ import annotations

import re
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def test_editable_install_maps_kernels_folder_into_the_package():
    import holowarp.kernels
    import holowarp.scenes

    assert Path(holowarp.kernels.__file__).resolve() == REPO / "kernels" / "__init__.py"
    assert Path(holowarp.scenes.__file__).resolve() == REPO / "scenes" / "__init__.py"
    # No generic top-level module: checked from a neutral folder, since pytest puts the repo
    # root itself on sys.path.
    probe = subprocess.run(
        [sys.executable, "-c", "import importlib.util as u; print(u.find_spec('kernels') is None)"],
        cwd="/", capture_output=True, text=True,
    )
    assert probe.stdout.strip() == "True", probe.stderr


def test_kernels_package_has_no_torch_imports():
    offenders = [
        p.name
        for p in (REPO / "kernels").rglob("*.py")
        if re.search(r"^\s*(import torch|from torch)", p.read_text(), flags=re.M)
    ]
    assert offenders == []


def test_wheel_installs_kernels_under_holowarp_and_ships_data(tmp_path):
    out = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", str(REPO), "--no-deps", "--no-build-isolation", "-q", "-w", str(tmp_path)],
        capture_output=True,
        text=True,
    )
    assert out.returncode == 0, out.stderr
    (wheel,) = tmp_path.glob("holowarp-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    assert "holowarp/kernels/__init__.py" in names
    assert not [n for n in names if n.startswith(("kernels/", "scenes/", "tests/"))]
    top = [n for n in names if n.endswith("top_level.txt")]
    assert zipfile.ZipFile(wheel).read(top[0]).decode().split() == ["holowarp"]
    for k in (REPO / "kernels").glob("*.py"):
        assert f"holowarp/kernels/{k.name}" in names
    for s in (REPO / "scenes").glob("*.toml"):
        assert f"holowarp/scenes/{s.name}" in names
    assert "holowarp/assets/bob/bob_tri.obj" in names


def test_ci_runs_the_readme_test_command_verbatim():
    readme = (REPO / "README.md").read_text()
    blocks = re.findall(r"```(?:bash|sh)?\n(.*?)```", readme, flags=re.S)
    commands = [line.strip() for b in blocks for line in b.splitlines() if "pytest" in line]
    assert len(commands) == 1, "the README must hold exactly one test command"
    ci = (REPO / ".ci" / "run").read_text()
    assert commands[0] in ci
    assert "torch==2.13.0" in commands[0] and commands[0].index("torch==2.13.0") < commands[0].index("-e")
