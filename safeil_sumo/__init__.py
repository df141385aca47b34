"""safeil-sumo: safe imitation learning of human-like highway driving, validated in SUMO."""

__version__ = "0.1.0"
