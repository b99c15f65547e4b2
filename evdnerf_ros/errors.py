"""One exception hierarchy for the whole toolkit.

Every message names the file / topic / byte offset at fault and says what would fix it;
the CLI prints the message on one line and exits with status 2.
"""

from __future__ import annotations


class EvdnerfError(Exception):
    """Base class of every error the toolkit raises on purpose."""


class InputError(EvdnerfError):
    """Bad input data or arguments (a file, a topic, a parameter)."""


class FormatError(InputError):
    """A byte stream or file that does not follow its declared format."""

    def __init__(self, message: str, *, source: str | None = None, offset: int | None = None):
        where = []
        if source:
            where.append(str(source))
        if offset is not None:
            where.append(f"byte offset {offset}")
        prefix = f"{': '.join(where)}: " if where else ""
        super().__init__(prefix + message)
        self.source = source
        self.offset = offset


class OutputExistsError(EvdnerfError):
    """Refusing to overwrite an existing output."""

    def __init__(self, path):
        super().__init__(f"{path}: output already exists; remove it or choose another path")
        self.path = path
