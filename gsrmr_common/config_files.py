"""Finding the package's YAML files by name: ``sandbox`` → ``…/config/<kind>/sandbox.yaml``.

Looked up, in order, in the source tree (``<repo>/config/<kind>``), the ament share directory of
``gsrmr`` (a ``colcon build`` or a ROS install), then ``<sys.prefix>/share/gsrmr/config/<kind>`` (where
``setup.py`` installs ``config/**/*.yaml`` for a plain pip install). A path (anything ending in
``.yaml``/``.yml``, or an existing file) is used as it is. No ROS import at module level.
"""

from __future__ import annotations

from pathlib import Path
import sys

PACKAGE = "gsrmr"
REPO_CONFIG_DIR = Path(__file__).resolve().parents[1] / "config"


def config_dirs(kind: str, repo_dir: Path | None = None) -> list[Path]:
    """Directories searched for ``config/<kind>/<name>.yaml`` (see the module docstring); ``repo_dir``
    replaces the source tree's ``config/<kind>``."""
    dirs = [repo_dir or REPO_CONFIG_DIR / kind]
    try:
        from ament_index_python.packages import get_package_share_directory

        dirs.append(Path(get_package_share_directory(PACKAGE)) / "config" / kind)
    except Exception:  # ament_index not installed, or gsrmr not in an ament prefix
        pass
    dirs.append(Path(sys.prefix) / "share" / PACKAGE / "config" / kind)
    return dirs


def resolve_config(name_or_path: str, kind: str, what: str, repo_dir: Path | None = None) -> Path:
    """The file for a bare name (searched in :func:`config_dirs`) or a path; FileNotFoundError names
    ``what`` (e.g. ``scene``) and every place searched."""
    p = Path(name_or_path)
    if p.suffix in (".yaml", ".yml") or p.exists():
        if not p.exists():
            raise FileNotFoundError(f"{what} file {p} does not exist")
        return p
    dirs = config_dirs(kind, repo_dir)
    for d in dirs:
        cand = d / f"{name_or_path}.yaml"
        if cand.exists():
            return cand
    raise FileNotFoundError(f"no {what} named {name_or_path!r} in {', '.join(str(d) for d in dirs)}")
