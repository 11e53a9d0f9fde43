"""Where the package's shipped files (config/, bags/) are, installed or in a checkout."""

from __future__ import annotations

from pathlib import Path

PACKAGE = 'sensing_nodes'


def share_dir() -> Path:
    """The package's share directory: the ament index's when installed, else the checkout root."""
    checkout = Path(__file__).resolve().parents[1]
    if (checkout / 'package.xml').is_file():
        return checkout
    try:
        from ament_index_python.packages import get_package_share_directory

        return Path(get_package_share_directory(PACKAGE))
    except (ImportError, LookupError, ValueError):
        return checkout


def config_file(name: str) -> Path:
    """Path of a file shipped in config/."""
    return share_dir() / 'config' / name
