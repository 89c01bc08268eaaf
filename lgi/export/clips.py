"""Where a long shot's USD keeps its frames: value clips in a folder beside the file (the layout only; the
writer is :func:`lgi.export.formats.write_usd`)."""

from __future__ import annotations

import os
from pathlib import Path

#: Frames per USD layer. A longer shot is written as value clips: the file holds the stage, the topology and the
#: UVs, and names a layer of this many frames' time samples each in the folder beside it (:func:`usd_clip_dir`),
#: which the DCC composes (USD's value clips). Writing holds one clip's samples (ICT: 320 MB per 1,000 frames),
#: where one layer of a 36,000-frame take would be 11.5 GB in memory.
USD_CLIP_FRAMES = 1000
#: What a clip folder holds (:func:`lgi.io.atomic.check_output`'s ``owned``).
USD_CLIP_CONTENTS = ("clip_*.usdc", "manifest.usda")


def usd_clip_dir(path: str | os.PathLike[str]) -> Path:
    """The folder of a long shot's value clips beside its USD file: ``shot.usdc`` -> ``shot.clips``."""
    path = Path(path)
    return path.with_name(f"{path.stem}.clips")
