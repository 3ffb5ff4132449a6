"""Folders on ``sys.path``: which of them hold installed distributions. Standard library only, because the fast
no-op path (msflow.fastpath) imports it."""

from __future__ import annotations

import os

#: the folder names pip installs distributions into
INSTALL_FOLDERS = ("site-packages", "dist-packages")


def holds_installed_packages(entry: str) -> bool:
    """Whether a ``sys.path`` entry is a folder pip installs distributions into (its mtime changes when one is
    installed, upgraded or removed), wherever it is: a virtualenv inside the project included."""
    return any(part in INSTALL_FOLDERS for part in os.path.abspath(entry or ".").split(os.sep))
