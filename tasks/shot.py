"""The per-shot tasks (defined in :mod:`lgi.orchestration.reconstruct`)."""

from lgi.orchestration.reconstruct import (
    choose_chunk,
    compare_task,
    finish_chunk,
    rays_task,
    review_task,
    track_footage,
    write_shot,
)

__all__ = ["choose_chunk", "compare_task", "finish_chunk", "rays_task", "review_task", "track_footage", "write_shot"]
