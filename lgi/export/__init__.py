"""Exports of reconstructions: USD, OpenEXR displacement maps."""
