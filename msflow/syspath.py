"""Folders on ``sys.path``: which of them hold installed distributions, and which belong to a project. Standard
library only, because the fast no-op path (msflow.fastpath) imports it."""

from __future__ import annotations

import os
from collections.abc import Iterable

#: the folder names pip installs distributions into
INSTALL_FOLDERS = ("site-packages", "dist-packages")


def holds_installed_packages(path: str) -> bool:
    """Whether ``path`` (a ``sys.path`` entry or a file) lies in a folder pip installs distributions into (its
    mtime changes when one is installed, upgraded or removed), wherever it is: a virtualenv inside the project
    included."""
    return any(part in INSTALL_FOLDERS for part in os.path.abspath(path or ".").split(os.sep))


def in_project(entry: str, roots: Iterable[str]) -> bool:
    """Whether a ``sys.path`` entry is a project's own folder (a root, each ending in the separator, or a folder
    inside one): project code is fingerprinted by content, so such a folder says nothing about the installed
    distributions. A site-packages folder inside a project (a ``.venv``) is not one of them."""
    path = os.path.abspath(entry or ".") + os.sep
    return not holds_installed_packages(entry) and any(path.startswith(root) for root in roots)
