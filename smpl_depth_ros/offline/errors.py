"""The exceptions of offline processing; `cli` maps them to exit codes."""
from __future__ import annotations


class ProcessBagError(RuntimeError):
    """An unusable input or option (exit code 1); the message says what to do."""


class InterruptedBeforeStart(RuntimeError):
    """Ctrl-C / SIGTERM before the first frame: nothing processed, nothing written."""


class BagReadError(RuntimeError):
    """The bag is damaged: `path` is the storage file, `position` where reading stopped."""

    def __init__(self, path, position: str, detail: str):
        super().__init__(f'{path}: unreadable {position}: {detail}')
        self.path = str(path)
        self.position = position
        self.detail = detail
