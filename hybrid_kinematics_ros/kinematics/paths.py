"""Where the package's own files are, and ``package://`` paths the way ROS users write them.

A plain ``colcon build`` copies the Python modules into site-packages and ``config/`` into the package's
share directory, so a path computed from ``__file__`` points nowhere there. The share directory comes from
the ament index; a source checkout (tests, the symlinked development install, a plain ``pip install -e``)
that is not on the index uses its own ``config/``.
"""

from __future__ import annotations

import re
from functools import lru_cache
from pathlib import Path

from hybrid_kinematics_ros.kinematics.errors import KinematicsError

PACKAGE = "hybrid_kinematics_ros"
SOURCE_ROOT = Path(__file__).resolve().parents[2]
# ``Path("package://p/x")`` collapses the double slash, so accept one or more.
_PACKAGE_URL = re.compile(r"^package:/+([^/]+)/(.+)$")
_FILE_URL = re.compile(r"^file://(/.*)$")


def _ament_share(package: str) -> Path:
    try:
        from ament_index_python.packages import PackageNotFoundError, get_package_share_directory
    except ImportError as exc:
        raise KinematicsError(f"cannot look up package '{package}': ament_index_python is not installed") from exc
    try:
        return Path(get_package_share_directory(package))
    except (PackageNotFoundError, ValueError) as exc:
        raise KinematicsError(
            f"package '{package}' is not in the ament index: source its workspace's install/setup.bash"
        ) from exc


@lru_cache(maxsize=1)
def share_dir() -> Path:
    """This package's files: the source checkout the code runs from, else the installed share directory."""
    if (SOURCE_ROOT / "package.xml").is_file() and (SOURCE_ROOT / "config").is_dir():
        return SOURCE_ROOT
    share = _ament_share(PACKAGE)
    if not (share / "config").is_dir():
        raise KinematicsError(f"{share}/config does not exist: the {PACKAGE} install is incomplete; rebuild it")
    return share


def config_dir() -> Path:
    """The shipped robot configs, URDFs and parameter files."""
    return share_dir() / "config"


def package_share(package: str) -> Path:
    """Share directory of any ament package (this one also from a source checkout)."""
    return share_dir() if package == PACKAGE else _ament_share(package)


def is_url(spec: str | Path) -> bool:
    return bool(_PACKAGE_URL.match(str(spec)) or _FILE_URL.match(str(spec)))


def resolve_path(spec: str | Path, relative_to: Path | None = None) -> Path:
    """A file path from ``package://pkg/rel``, ``file:///abs`` or a plain path.

    A plain relative path is taken relative to ``relative_to`` when given (a robot config's URDF entry is
    relative to the config file), else to the current directory. Existence is not checked here: callers
    name the parameter or field in their own message.
    """
    text = str(spec)
    match = _PACKAGE_URL.match(text)
    if match:
        return package_share(match.group(1)) / match.group(2)
    match = _FILE_URL.match(text)
    if match:
        return Path(match.group(1))
    path = Path(text).expanduser()
    if relative_to is not None and not path.is_absolute():
        return relative_to / path
    return path
