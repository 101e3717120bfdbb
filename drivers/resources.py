"""Package data as files on disk, found with :mod:`importlib.resources`.

Defaults (the simulator's reference camera, its worlds, the service's default config and lens
tables) ship inside the packages, so a non-editable install finds them wherever it is installed
and whatever the working directory. Nothing here knows a source-tree layout.
"""

from __future__ import annotations

import atexit
import contextlib
from importlib import resources
from pathlib import Path

__all__ = ["ResourceNotFoundError", "packaged_file", "packaged_names"]

# Files extracted from a zipped install live until the process ends (see packaged_file).
_EXTRACTED = contextlib.ExitStack()
atexit.register(_EXTRACTED.close)


class ResourceNotFoundError(LookupError):
    """A named packaged file does not exist; the message lists the names that do."""


def packaged_file(package: str, *parts: str) -> Path:
    """The path on disk of the data file ``parts`` inside ``package``.

    Raises ResourceNotFoundError when the package holds no such file.
    """
    resource = resources.files(package).joinpath(*parts)
    if not resource.is_file():
        raise ResourceNotFoundError(f"{package} holds no file {'/'.join(parts)}")
    if isinstance(resource, Path):  # a normal (directory) install: the file itself
        return resource
    # A zipped install: extract once and keep the copy for the life of the process.
    return _EXTRACTED.enter_context(resources.as_file(resource))


def packaged_names(package: str, directory: str, suffix: str) -> tuple[str, ...]:
    """Stems of the files ending in ``suffix`` in ``directory`` of ``package``, sorted."""
    folder = resources.files(package).joinpath(directory)
    if not folder.is_dir():
        return ()
    return tuple(
        sorted(
            entry.name.removesuffix(suffix)
            for entry in folder.iterdir()
            if entry.is_file() and entry.name.endswith(suffix)
        )
    )
