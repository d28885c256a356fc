"""``/messages``: the DBC messages the cell decodes, the file of each and its channels.

The page builds a panel per message of a user's DBC file (``--dbc``) from it; a message of
the cell's own files (``dbc/``, a plugin's) says ``"user": false``.
"""

from pathlib import Path
from typing import Any

from fastapi import APIRouter

from ..deps import CellDep

router = APIRouter(prefix="/messages", tags=["channels"])


def _user_paths(settings: Any) -> list[Path]:
    paths = getattr(settings, "dbc", None) or ()
    if isinstance(paths, (str, Path)):
        paths = [paths]
    return [Path(p).resolve() for p in paths]


@router.get("", name="list messages",
            description="Every DBC message the cell decodes: its name, frame ID, the file that "
                        "defines it, whether that file is a user's (`--dbc`), and the channels "
                        "of its signals (in the DBC's order).")
def list_messages(cell: CellDep) -> list[dict[str, Any]]:
    user = _user_paths(cell.settings)
    out: dict[str, dict[str, Any]] = {}
    for channel, info in cell.runtime.db.signals.items():
        m = out.get(info.message)
        if m is None:
            f = Path(info.file).resolve() if info.file else None
            m = out[info.message] = {
                "name": info.message, "frame_id": info.frame_id,
                "file": f.name if f else None,
                "user": bool(f and any(f == p or p in f.parents for p in user)),
                "channels": []}
        m["channels"].append(channel)
    return sorted(out.values(), key=lambda m: m["frame_id"])
