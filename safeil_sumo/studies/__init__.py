"""The sections of ``python -m safeil_sumo.results``, one module per section (or per small group
of related ones): each holds its section's runner, its plots and its part of
``results/README.md`` or ``results/studies.md``; ``shared`` holds what they share. The command
line, its section order and the two pages' assembly are ``safeil_sumo/results.py``."""
