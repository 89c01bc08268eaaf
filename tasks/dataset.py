"""The dataset and index tasks (defined in :mod:`lgi.orchestration.rebuild`)."""

from lgi.orchestration.rebuild import (
    assemble,
    augment,
    fit_rig,
    natural_neighbours,
    point_clouds,
    publish,
    read_shapes,
    stabilise,
    verify,
)

__all__ = ["assemble", "augment", "fit_rig", "natural_neighbours", "point_clouds", "publish", "read_shapes",
           "stabilise", "verify"]
