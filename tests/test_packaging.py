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


def _readme_commands() -> dict[str, str]:
    """{module: the README table's usage text} for every ``python -m holowarp.X`` row."""
    readme = (REPO / "README.md").read_text()
    rows = re.findall(r"^\| `python -m (holowarp[\w.]*) ([^`]*)` \|", readme, flags=re.M)
    return {m: usage for m, usage in rows}


def test_every_flag_the_readme_documents_is_a_real_option_of_its_command():
    import importlib

    rows = _readme_commands()
    assert {"holowarp.reconstruct", "holowarp.gs2d", "holowarp.synth", "holowarp.evaluate", "holowarp.simulate",
            "holowarp.convert", "holowarp.baselines.visual_hull", "holowarp.bench"} <= set(rows)
    for module, usage in rows.items():
        mod = importlib.import_module(module if module != "holowarp.bench" else "holowarp.bench.__main__")
        flags = set(re.findall(r"(--[a-z][a-z0-9-]*)", usage))
        if module == "holowarp.bench":
            text = mod._help()
            assert all(f in text for f in flags), (module, flags)
            continue
        known = {o for a in mod.build_parser()._actions for o in a.option_strings}
        assert flags <= known, (module, sorted(flags - known))


def test_commands_share_one_convention_for_device_and_quiet():
    import importlib

    for module in ("holowarp.reconstruct", "holowarp.gs2d", "holowarp.synth", "holowarp.evaluate",
                   "holowarp.simulate", "holowarp.convert", "holowarp.baselines.visual_hull", "holowarp.poses"):
        known = {o for a in importlib.import_module(module).build_parser()._actions for o in a.option_strings}
        assert {"--device", "--quiet"} <= known, module
    from holowarp.cli import PRESET_NAMES

    for module in ("holowarp.reconstruct", "holowarp.gs2d"):
        (preset,) = [a for a in importlib.import_module(module).build_parser()._actions if "--preset" in a.option_strings]
        assert tuple(preset.choices) == PRESET_NAMES == ("fast", "paper")


def test_installed_scripts_point_at_real_entry_points():
    import importlib

    try:
        import tomllib
    except ModuleNotFoundError:  # Python < 3.11
        import tomli as tomllib
    scripts = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]
    assert len(scripts) >= 8
    for name, target in scripts.items():
        module, func = target.split(":")
        assert callable(getattr(importlib.import_module(module), func)), name
        assert name in (REPO / "README.md").read_text(), f"{name} is not listed in the README"
