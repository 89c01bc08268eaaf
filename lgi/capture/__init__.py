"""From cameras to bundles: camera models, calibration, dot detection, tracking, head stabilisation,
the bundles file."""
