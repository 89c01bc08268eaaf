"""The ``manifest.json`` of a stored directory (a dataset, an index): read and checked in one place."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from lgi.errors import InputError


def read_manifest(directory: str | Path, fmt: str, version: int, what: str) -> dict[str, Any]:
    """The manifest of ``directory``, a stored ``what`` ("shape dataset", "LGI index") of format ``fmt``, or an
    :class:`InputError` naming the file: missing, not JSON, not an object, another format, a newer version."""
    directory = Path(directory)
    path = directory / "manifest.json"
    if not path.is_file():
        raise InputError(f"not a{'n' if what[0] in 'aeiouAEIOUL' else ''} {what} (no manifest.json)", path=directory)
    try:
        manifest = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        line = getattr(exc, "lineno", None)
        raise InputError(f"manifest is not valid JSON: {getattr(exc, 'msg', exc)}", path=path, line=line) from None
    if not isinstance(manifest, dict) or manifest.get("format") != fmt:
        got = manifest.get("format") if isinstance(manifest, dict) else type(manifest).__name__
        raise InputError(f"manifest format is {got!r}, expected {fmt!r}", path=path)
    if manifest.get("format_version", 0) > version:
        raise InputError(f"{what} format version {manifest['format_version']} is newer than this lgi reads "
                         f"({version})", path=path)
    return manifest
