"""The LGI index: per-bundle point clouds and simplices, natural-neighbour weights, the smooth correction."""
