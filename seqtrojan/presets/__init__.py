"""The YAML presets shipped with the package (this folder; the repository's ``configs/`` points here).

Training presets (``seqtrojan train --config NAME``): ``smoke``, ``clean_7x7``, ``onoff_7x7``, ``clean_s17_h30``,
``trojan_s17_h30``. Reproduction scales (``seqtrojan reproduce --scale NAME``): ``reproduce_smoke``,
``reproduce_paper``, ``reproduce_headline``. Matrix scales (``seqtrojan matrix --scale NAME``): ``matrix_smoke``,
``matrix_paper``. Training presets on Gymnasium envs (``env.kind: gymnasium``, also ``seqtrojan train --config
NAME``): ``minigrid_two_goals``, ``minigrid_memory`` then ``minigrid_memory_backdoor``. Wherever a preset is
asked for, a path to a YAML file works too.
"""

from __future__ import annotations

from pathlib import Path

from seqtrojan.errors import ConfigError

PRESETS_DIR = Path(__file__).resolve().parent


def list_presets() -> list[str]:
    """The names of the shipped presets, sorted."""
    return sorted(p.stem for p in PRESETS_DIR.glob("*.yaml"))


def resolve_preset(name: str | Path) -> Path:
    """A preset's YAML file: ``name`` itself when it is an existing file, else the shipped preset of that name
    (with or without ``.yaml``)."""
    path = Path(name)
    if path.is_file():
        return path
    stem = path.name.removesuffix(".yaml")
    if path.name == str(name) and stem:  # a bare name, not a path with folders
        packaged = PRESETS_DIR / f"{stem}.yaml"
        if packaged.is_file():
            return packaged
    raise ConfigError(
        f"preset {str(name)!r} not found: that file does not exist and no shipped preset has that name "
        f"(shipped: {', '.join(list_presets())})"
    )
