"""Measuring-line planning, beam envelope, G-code writers and identification design.

Pure planning math on top of the :mod:`xmalign` core; no drivers, no simulator.
"""
