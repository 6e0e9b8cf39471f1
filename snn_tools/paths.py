"""Where the package's share files are: the ament index when installed, the source tree otherwise."""

from __future__ import annotations

from pathlib import Path

PACKAGE = 'snn_rendezvous'
SOURCE_ROOT = Path(__file__).resolve().parents[1]
#: The package's Fast DDS profile (config/fastdds.xml: reliable writers heartbeat every 100 ms,
#: docs/decisions.md, 38) and the variable that points Fast DDS at it.
DDS_PROFILE = 'fastdds.xml'
DDS_PROFILE_VARIABLE = 'FASTRTPS_DEFAULT_PROFILES_FILE'


def share_directory() -> Path:
    """share/snn_rendezvous of the installed package, or the source checkout (editable installs
    do not install data files)."""
    try:
        from ament_index_python.packages import get_package_share_directory
        return Path(get_package_share_directory(PACKAGE))
    except (ImportError, LookupError, OSError, ValueError):  # not installed, or no AMENT_PREFIX_PATH
        return SOURCE_ROOT


def config_file(name: str = 'rendezvous.yaml') -> Path:
    """A file of config/ (a path given by the user is returned unchanged if it exists)."""
    candidate = Path(name)
    if candidate.exists():
        return candidate.resolve()
    for root in (share_directory(), SOURCE_ROOT):
        path = root / 'config' / name
        if path.exists():
            return path
    raise FileNotFoundError(f'no config file {name!r} in {share_directory() / "config"} or {SOURCE_ROOT / "config"}')


def replace_between_markers(doc: Path, begin: str, end: str, text: str) -> bool:
    """Write ``text`` between the ``begin`` and ``end`` marker lines of ``doc`` (a generated
    table inside hand-written docs); False, nothing written, when ``doc`` or a marker is missing."""
    if not doc.exists():
        return False
    content = doc.read_text()
    if begin not in content or end not in content:
        return False
    head, rest = content.split(begin, 1)
    doc.write_text(head + begin + '\n' + text + end + rest.split(end, 1)[1])
    return True
