"""Prefect flows built from the tasks in ``tasks/``."""
