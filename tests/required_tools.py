"""Skips for a missing LinuxCNC that CI turns into failures.

A test that needs LinuxCNC (Debian ``linuxcnc-uspace``: a headless LinuxCNC, its
Python module, ``rs274``, its sample configurations) or ``halcompile``
(``linuxcnc-uspace-dev``) is skipped where they are missing, so that the suite
runs anywhere. ``.ci/run`` installs them and sets ``XMALIGN_REQUIRE_LINUXCNC=1``:
then a missing one fails the test instead, and CI cannot pass by skipping them.
"""

from __future__ import annotations

import os

import pytest

#: Set by .ci/run: a missing LinuxCNC, halcompile or rs274 fails instead of skipping.
LINUXCNC_REQUIRED = os.environ.get("XMALIGN_REQUIRE_LINUXCNC", "") == "1"


def skip_unless_required(reason: str) -> None:
    """Skip the test for ``reason``, or fail it when LinuxCNC is required."""
    if LINUXCNC_REQUIRED:
        pytest.fail(f"{reason} (XMALIGN_REQUIRE_LINUXCNC=1: it is required)", pytrace=False)
    pytest.skip(reason)
