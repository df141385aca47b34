"""Background traffic: SUMO's own vehicles from a net's route files, as the ego's leaders.

Densities scale the flows of the shipped route files (SUMO ``--scale``).
"""

from __future__ import annotations

# --traffic density -> factor on the flows of the route files [-]
DENSITIES: dict[str, float] = {"light": 0.5, "default": 1.0, "dense": 2.0}
