"""Deployment entry point of the capture-session flow (``prefect.yaml``); the flow is
:func:`lgi.orchestration.capture.capture_session`."""

from __future__ import annotations

from lgi.orchestration.capture import capture_session

__all__ = ["capture_session"]
