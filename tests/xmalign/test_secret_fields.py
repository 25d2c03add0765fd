"""Secret fields in files people write: their value never appears in an error message.

A secret is a pydantic ``SecretStr`` anywhere in a field's type (Optional, a list,
a nested model), xmalign's :data:`~xmalign.formats.common.Secret`, or a field
marked ``Field(json_schema_extra={"secret": True})``.
"""

from __future__ import annotations

from typing import Annotated

import pytest
from pydantic import Field, SecretStr

from xmalign.errors import InputError
from xmalign.formats.common import Secret, StrictFileModel, validate


class _Login(StrictFileModel):
    password: Secret
    token: Annotated[int, Field(json_schema_extra={"secret": True})] = 0
    pins: list[SecretStr] = []
    user: str = "u"


class _Config(StrictFileModel):
    login: _Login | None = None
    logins: dict[str, _Login] = {}


@pytest.mark.parametrize(
    ("data", "key", "value"),
    [
        ({"login": {"password": 47.11}}, "login.password", "47.11"),
        ({"login": {"password": True}}, "login.password", "True"),
        ({"login": {"password": "ok", "token": "t0ps3cret"}}, "login.token", "t0ps3cret"),
        ({"login": {"password": "ok", "pins": ["1", 98765]}}, "login.pins.1", "98765"),
        ({"logins": {"cnc": {"password": [31337]}}}, "logins.cnc.password", "31337"),
    ],
)
def test_a_secret_is_named_by_its_key_only(data: dict, key: str, value: str) -> None:
    with pytest.raises(InputError, match=f"f.yaml: key '{key}'") as caught:
        validate(_Config, data, "f.yaml")
    assert value not in str(caught.value) and caught.value.__cause__ is None


def test_other_keys_still_show_their_value() -> None:
    with pytest.raises(InputError, match=r"key 'login.user': 42 must be a valid string"):
        validate(_Config, {"login": {"password": "ok", "user": 42}}, "f.yaml")


def test_a_whole_number_is_the_password_as_written() -> None:
    config = validate(_Config, {"login": {"password": 4711}}, "f.yaml")
    assert config.login is not None and config.login.password.get_secret_value() == "4711"
    assert "4711" not in repr(config)
