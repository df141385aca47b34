"""The report card of ``safeil-evaluate``: its sections over the engines, their figures and
verdicts."""
