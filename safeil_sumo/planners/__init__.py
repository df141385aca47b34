"""The planners: the analytic and IDM planners, the inference-time safety filter (pure numpy) and
the registry that names every planner, the shipped checkpoints included."""
