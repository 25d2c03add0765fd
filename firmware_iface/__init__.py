"""Drivers: how commands reach the positioning units, the interferometer and the CNC."""
