"""The design loop (issue 25, item 6): what a sensor designer runs before fabricating.

``sweep`` builds the designs, ``score`` scores a design's tactile images, ``loop`` runs
the sweep with the fast path and checks the best and the worst with the reference,
``report`` writes the report, ``cli`` is ``tactile-sim design``.
"""
