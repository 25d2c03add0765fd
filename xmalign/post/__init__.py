"""Post-processing: from the six lines' channels to the ISO 230-1 error tables.

``lines`` groups the measurement rows by plan line, ``setup_terms`` models what
the setup adds to the channels, ``solve`` is the weighted least-squares fit of
the error tables (seed 000: B-spline discretisation, GUM propagation) and
``iso230_2`` the positioning figures of each axis line.
"""
