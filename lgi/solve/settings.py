"""The solver's settings, declared once: :class:`~lgi.solve.solver.LGISolver` takes them, and the reconstruct job
declares its flags for the shared ones from them (:func:`lgi.options.same_as`)."""

from __future__ import annotations

from dataclasses import dataclass

from lgi.options import declared, option

#: Far field (cm of UV-geodesic distance to the nearest bundle): up to the first value every vertex mixes the
#: bundles' own weights; beyond the second it takes the frame's global fit; in between a smooth ramp.
FAR_FIELD = (0.5, 1.5)


@declared
@dataclass(frozen=True)
class SolverSettings:
    """How :class:`~lgi.solve.solver.LGISolver` chooses and blends each frame's shapes."""

    temporal_weight: float = option(
        0.02, "preference for the previous frame's shapes, mm of neighbour misfit: added to a candidate's score "
        "per unit share of its shapes the previous frame's choice for the bundle does not use (default "
        "%(default)s; 0 = none)", group="method", metavar="MM", units="mm")
    spatial_weight: float = option(
        1e-3, "tie-break toward shapes the neighbours agree on, mm: a second pass prefers the shapes the bundle's "
        "natural neighbours and the whole frame chose in the first, and lets a bundle take a neighbour's mixture "
        "(default %(default)s; 0 = none)", group="method", metavar="MM", units="mm")
    alias_min_weight: float = option(
        0.1, "a candidate's corner tries the shapes merged into its cloud point when its weight is at least this")
    correct_residuals: bool = option(
        True, "interpolate the bundles' remaining residuals smoothly, so that the surface passes through every "
        "bundle")
    tolerance: float = option(1e-9, "barycentric tolerance of the containment test")
    n_project: int = option(3, "hull facets tried when projecting a bundle")
    top_k: int = option(
        4, "containing simplices are pre-screened by their neighbour misfit; this many distinct ones get the full "
        "score (alias sweep, temporal and agreement terms)")
    jaw: str = option(
        "auto", "with an index built with a jaw rig: 'auto' estimates each frame's jaw from the bundles that move "
        "with it (or takes it from solve_frame(jaw=...)); 'none' is refused for such an index (its shapes are "
        "unskinned)", choices=("auto", "none"))
    method: str = option(
        "local", "local: a global fit of the bounded shape weights (and the jaw with a rig) per frame, then each "
        "bundle's weights refitted to the bundle and its natural neighbours over the shapes the global fit uses "
        "and those of its best containing simplex, the simplex kept where it fits the neighbourhood better; "
        "simplex: the paper's choice among containing simplices only (the jaw from the global fit)",
        choices=("local", "simplex"))
    local_prior: float = option(1e-6, "ridge of the local fits toward the global weights, per unit weight squared",
                                units="cm^2")
    noise: float = option(
        0.0, "the bundles' measurement noise per coordinate (or (3,) per axis): 0, exact bundles the surface passes "
        "through; above 0, measurements: a sequence's trajectories are smoothed first, each bundle's local fit is "
        "held toward the global weights by the noise left, no simplex is taken, and the surface passes through "
        "each bundle only by the share of its residual that is the face", units="mm")
    far_field: tuple[float, float] | None = option(
        FAR_FIELD, "vertices farther than the first distance from every bundle (UV-geodesic) blend toward the "
        "frame's global fit, wholly at the second (a smoothstep ramp), as far as their bundles' weights predict "
        "the bundles beyond their neighbourhood worse than the global fit; bundles' own triangles never blend. "
        "None: the bundles' weights everywhere (the paper's blend)", units="cm")
