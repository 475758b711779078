"""Simulation scenarios as data (TOML), installed as ``holowarp.scenes``.

``drop.toml`` and ``compress.toml`` ship with the package. Copy one, edit it, and pass its
path to ``python -m holowarp.simulate MESH --scene PATH.toml``.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["scene_path", "builtin_scenes"]

_HERE = Path(__file__).resolve().parent


def builtin_scenes() -> list[str]:
    """Names of the scenes shipped with holowarp (file stems)."""
    return sorted(p.stem for p in _HERE.glob("*.toml"))


def scene_path(name_or_path: str) -> Path:
    """Resolve a built-in scene name (``"drop"``) or a path to a ``.toml`` file."""
    p = Path(name_or_path)
    if p.suffix == ".toml":
        if not p.is_file():
            raise FileNotFoundError(f"scene file {p}: no such file")
        return p
    cand = _HERE / f"{name_or_path}.toml"
    if not cand.is_file():
        raise FileNotFoundError(
            f"scene {name_or_path!r}: not a built-in scene ({', '.join(builtin_scenes()) or 'none'})"
            " and not a path ending in .toml"
        )
    return cand
