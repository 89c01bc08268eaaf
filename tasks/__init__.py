"""Prefect tasks: thin wrappers over the ``lgi`` library, one per pipeline stage."""
