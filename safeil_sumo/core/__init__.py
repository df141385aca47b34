"""The pure core: frames and polylines, B-splines, the planner's features, the ``Policy`` contract,
atomic file writes. numpy only; everything else builds on it."""
