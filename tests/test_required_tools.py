"""A missing LinuxCNC skips a test, or fails it under XMALIGN_REQUIRE_LINUXCNC=1 (.ci/run)."""

from __future__ import annotations

import pytest
import required_tools


@pytest.mark.parametrize(
    ("required", "outcome"), [(False, pytest.skip.Exception), (True, pytest.fail.Exception)]
)
def test_a_missing_tool_skips_unless_required(
    monkeypatch: pytest.MonkeyPatch, required: bool, outcome: type[BaseException]
) -> None:
    monkeypatch.setattr(required_tools, "LINUXCNC_REQUIRED", required)
    with pytest.raises(outcome, match="rs274 is missing"):
        required_tools.skip_unless_required("rs274 is missing")


def test_ci_requires_linuxcnc() -> None:
    ci = (required_tools.__file__.rsplit("/tests/", 1)[0]) + "/.ci/run"
    with open(ci, encoding="utf-8") as script:
        assert "export XMALIGN_REQUIRE_LINUXCNC=1" in script.read()
