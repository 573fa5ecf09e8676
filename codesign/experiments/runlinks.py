"""No run writes through a symbolic link: a link inside a folder a run writes into (``.hydra`` pointing at another
folder, a log pointing at another file) would let Hydra's config records and the run's own writes change files
outside the run folder. Such a folder is refused before anything is written there. The path leading to the run
folder may pass through links (an ``outputs`` linked to a larger disk): only what lies inside the folder counts."""
from __future__ import annotations

import os
from pathlib import Path

from codesign.errors import ConfigError


def links_inside(folder: Path) -> list[Path]:
    """Every symbolic link inside ``folder`` (at any depth; links to folders are not entered)."""
    found = []
    for top, dirs, files in os.walk(folder, followlinks=False):
        found += [Path(top) / n for n in (*dirs, *files) if os.path.islink(os.path.join(top, n))]
    return sorted(found)


def refuse_links(folder: Path, key: str) -> None:
    """ConfigError naming ``key``, the folder and its first link when anything inside ``folder`` is a symlink."""
    folder = Path(folder).absolute()
    links = links_inside(folder) if folder.is_dir() else []
    if not links:
        return
    first = links[0]
    more = f" (and {len(links) - 1} more link(s))" if len(links) > 1 else ""
    raise ConfigError(key, str(folder), f"holds a symbolic link: {first.relative_to(folder)} -> "
                      f"{os.readlink(first)}{more}; a run never writes through a link (it would change files "
                      f"outside its folder): replace the link by a real file or folder, or choose another folder "
                      f"with {key}=PATH")


def refuse_dangling(folder: Path, key: str) -> None:
    """ConfigError naming ``key`` when ``folder`` (or a folder on the way to it) is a symbolic link to nothing:
    making the run folder would have to follow the link (mkdir fails on it, or creates its target elsewhere)."""
    folder = Path(folder).absolute()
    for path in (folder, *folder.parents):
        if path.is_symlink() and not path.exists():
            where = "is" if path == folder else f"lies under {path}, which is"
            raise ConfigError(key, str(folder), f"{where} a symbolic link to {os.readlink(path)}, which does not "
                              f"exist; a run never follows a link to make its folder: create the target folder "
                              f"first, or choose another folder with {key}=PATH")
