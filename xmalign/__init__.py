"""xmalign: automatic setup and evaluation of a 6-DOF laser calibrator on positioning units."""

__version__ = "0.1.0"
