"""Which motions are recorded clips (BVH files, shipped CMU clips) rather than the simulated motions of ``motions``.

Kept free of heavy imports: stage specs call :func:`motion_files` to put a clip's content digest into the cache
key. ``source.motion`` takes a built-in motion name, a path to a ``.bvh`` file, or ``cmu/<subject_trial>`` for a
clip shipped in ``eventcap/body/assets/cmu/`` (see the README there for the source and what was trimmed).
"""

from __future__ import annotations

from pathlib import Path

#: Folder of the shipped CMU clips (``cmu/13_17`` -> ``<folder>/13_17.bvh``).
CMU_DIR = Path(__file__).parent / "assets" / "cmu"
CMU_PREFIX = "cmu/"


def is_clip(name: str) -> bool:
    """True for ``cmu/<subject_trial>`` and for anything naming a ``.bvh`` file."""
    name = str(name).strip()
    return name.startswith(CMU_PREFIX) or name.lower().endswith(".bvh")


def shipped_clips() -> list[str]:
    """Names (``cmu/<subject_trial>``) of the clips shipped with the package, sorted."""
    return sorted(CMU_PREFIX + p.stem for p in CMU_DIR.glob("*.bvh"))


def clip_path(name: str) -> Path:
    """The BVH file of a clip name; FileNotFoundError naming what exists when there is none."""
    name = str(name).strip()
    if name.startswith(CMU_PREFIX):
        path = CMU_DIR / f"{name[len(CMU_PREFIX):]}.bvh"
        if not path.is_file():
            raise FileNotFoundError(f"motion {name!r}: no such shipped clip; shipped: {', '.join(shipped_clips())}")
        return path
    path = Path(name).expanduser()
    if not path.is_file():
        raise FileNotFoundError(f"motion {name!r}: BVH file not found (relative paths start at {Path.cwd()})")
    return path


def motion_files(value: str) -> list[str]:
    """The files a ``source.motion`` value plays (their contents enter the cache key); [] for built-in motions."""
    names = [n.strip() for n in str(value).split(",") if n.strip()]
    out = []
    for n in names:
        if is_clip(n):
            try:
                out.append(str(clip_path(n)))
            except FileNotFoundError:
                out.append(n)  # the digest step reports the missing file with the config key
    return out
