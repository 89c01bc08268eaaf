"""The per-shot tasks (defined in :mod:`lgi.orchestration.reconstruct`)."""

from lgi.orchestration.reconstruct import choose_chunk, finish_chunk, track_footage, write_shot

__all__ = ["choose_chunk", "finish_chunk", "track_footage", "write_shot"]
