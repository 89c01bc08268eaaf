"""Retargeting: actor-specific rigs from a template rig (LGI paper 7.7)."""
