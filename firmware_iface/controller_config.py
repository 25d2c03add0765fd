"""``units.yaml``: the controllers a run follows (``machine_position: source: mtconnect`` or
``sinumerik``), and opening them (docs/hardware.md, "Following the controller").

    machine_position:
      source: mtconnect
      mtconnect:
        url: http://192.168.10.30:5000
        device: VMC-3Axis          # default: the agent's only device
        axes: [X, Y, Z]            # the Linear components giving x, y, z
        timeout_s: 2.0             # default: timeouts.io_s
        settle_s: 0.2              # standstill: unchanged this long ...
        standstill_mm: 0.002       # ... within this
        program_name: run          # xmalign's program as the agent's Program names it
                                   # (default: the program file's name, run)

    machine_position:
      source: sinumerik
      sinumerik:
        endpoint: opc.tcp://192.168.214.241:4840
        user: xmalign
        password_env: XMALIGN_OPCUA_PASSWORD   # or password: ...
        security_policy: Basic256Sha256        # None, Basic256Sha256, Aes128_Sha256_RsaOaep, ...
        certificate: xmalign-cert.der
        private_key: xmalign-key.pem
        program: Sinumerik/FileSystem/Part Program/XMALIGN.MPF  # selected before the run
        copy_program: true         # and written there from the plan first (FsWrite)
        program_name: XMALIGN      # default: program's file name, else run
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, SecretStr, field_validator, model_validator

from xmalign.errors import InputError
from xmalign.formats.common import Secret, StrictFileModel
from xmalign.roles import Clock, MachinePositionSource

Seconds = Annotated[float, Field(gt=0, le=600)]
SettleSeconds = Annotated[float, Field(gt=0, le=60)]
StandstillMm = Annotated[float, Field(gt=0, le=1)]
#: A program's name as a controller reports it (``run``, ``O1000``, ``/home/cnc/run.ngc``).
ProgramName = Annotated[str, Field(min_length=1, max_length=200, pattern=r"^\S(.*\S)?$")]
#: Where the SINUMERIK's OPC UA file system keeps main programs (configuration manual 7.5).
NC_FILE_SYSTEM = "Sinumerik/FileSystem/"


class MTConnectConfig(StrictFileModel):
    """An MTConnect agent xmalign reads the position from (read-only)."""

    url: Annotated[str, Field(pattern=r"^https?://\S+$")]
    #: The device's name or uuid in the agent (default: its only device).
    device: str | None = None
    axes: Annotated[list[str], Field(min_length=3, max_length=3)] = ["X", "Y", "Z"]
    timeout_s: Seconds | None = None
    settle_s: SettleSeconds = 0.2
    standstill_mm: StandstillMm = 0.002
    #: xmalign's program as the agent's ``Program`` names it (default: the program file's).
    program_name: ProgramName | None = None


class SinumerikConfig(StrictFileModel):
    """A SINUMERIK 840D sl / ONE whose OPC UA server xmalign reads the position from."""

    endpoint: Annotated[str, Field(pattern=r"^opc\.tcp://\S+$")]
    channel: Annotated[int, Field(ge=1, le=30)] = 1
    #: The channel's machine axes giving x, y, z (1-based).
    axes: Annotated[list[Annotated[int, Field(ge=1, le=31)]], Field(min_length=3, max_length=3)] = [
        1,
        2,
        3,
    ]
    mode_group: Annotated[int, Field(ge=1, le=10)] = 1
    length_unit: Literal["mm", "inch"] = "mm"
    user: str | None = None
    password: Secret | None = None
    #: The name of an environment variable holding the password (keeps it out of the file).
    password_env: str | None = None
    security_policy: Literal[
        "None", "Basic256Sha256", "Aes128_Sha256_RsaOaep", "Aes256_Sha256_RsaPss"
    ] = "None"
    security_mode: Literal["Sign", "SignAndEncrypt"] = "SignAndEncrypt"
    certificate: Path | None = None
    private_key: Path | None = None
    server_certificate: Path | None = None
    #: user (user and password), certificate (the client certificate), anonymous.
    identity: Literal["user", "certificate", "anonymous"] | None = None
    timeout_s: Seconds | None = None
    settle_s: SettleSeconds = 0.2
    standstill_mm: StandstillMm = 0.002
    #: xmalign's program in the NC's OPC UA file system: selected before the run.
    program: str | None = None
    #: Write the plan's program to ``program`` before selecting it (CopyFileToServer).
    copy_program: bool = False
    #: xmalign's program as the NC names it (default: the file name of ``program``).
    program_name: ProgramName | None = None

    @field_validator("program")
    @classmethod
    def _main_program_path(cls, program: str | None) -> str | None:
        if program is None:
            return None
        name = program.rsplit("/", 1)[-1]
        stem, _, extension = name.rpartition(".")
        if (
            not program.startswith(NC_FILE_SYSTEM)
            or extension.lower() != "mpf"
            or not stem
            or "." in stem
            or name != name.strip()
        ):
            raise ValueError(
                f"expected a main program's path in the NC's file system, e.g."
                f" '{NC_FILE_SYSTEM}Part Program/XMALIGN.MPF' (one extension, .mpf)"
            )
        return program

    @model_validator(mode="after")
    def _consistent(self) -> SinumerikConfig:
        if (self.certificate is None) != (self.private_key is None):
            raise ValueError("give both 'certificate' and 'private_key', or neither")
        if self.security_policy != "None" and self.certificate is None:
            raise ValueError(f"security_policy {self.security_policy} needs 'certificate'")
        if self.password is not None and self.password_env is not None:
            raise ValueError("give 'password' or 'password_env', not both")
        if self.login == "user" and self.user is None:
            raise ValueError("identity: user needs 'user'")
        if self.login == "certificate" and self.certificate is None:
            raise ValueError("identity: certificate needs 'certificate'")
        if self.copy_program and self.program is None:
            raise ValueError("copy_program needs 'program' (where on the NC to write it)")
        return self

    @property
    def login(self) -> Literal["user", "certificate", "anonymous"]:
        """The identity: as given, else user when a user is named, else anonymous."""
        return self.identity or ("user" if self.user is not None else "anonymous")


def expected_program(config: MTConnectConfig | SinumerikConfig, default: str) -> tuple[str, str]:
    """xmalign's program as the controller names it, and the key that says so: the
    section's ``program_name``, else the SINUMERIK's ``program``, else ``default`` (the
    name of the program file ``xmalign program`` writes, or the number in it on a Fanuc)."""
    kind = "mtconnect" if isinstance(config, MTConnectConfig) else "sinumerik"
    key = f"machine_position.{kind}.program_name"
    if config.program_name is not None:
        return config.program_name, key
    if isinstance(config, SinumerikConfig) and config.program is not None:
        return config.program, f"machine_position.{kind}.program"
    return default, f"{key}, default: the program file's name"


def resolve_paths(config: SinumerikConfig | None, base_dir: Path) -> SinumerikConfig | None:
    """Certificate paths relative to the ``units.yaml``'s folder."""
    if config is None:
        return None
    keys = ("certificate", "private_key", "server_certificate")
    update = {key: base_dir / path for key in keys if (path := getattr(config, key)) is not None}
    return config.model_copy(update=update)


def open_mtconnect_source(
    config: MTConnectConfig,
    io_s: float,
    closers: list[Callable[[], None]],
    clock: Clock | None = None,
) -> MachinePositionSource:
    """The agent of ``config``, probed; its closer appended to ``closers``."""
    from firmware_iface.mtconnect import open_mtconnect

    machine = open_mtconnect(
        config.url,
        config.timeout_s or io_s,
        config.device,
        config.axes,
        config.settle_s,
        config.standstill_mm,
        clock,
    )
    closers.append(machine.close)
    return machine


def open_sinumerik_source(
    config: SinumerikConfig,
    io_s: float,
    closers: list[Callable[[], None]],
    clock: Clock | None = None,
) -> MachinePositionSource:
    """A session with the SINUMERIK of ``config``; its closer appended to ``closers``."""
    try:
        from firmware_iface.sinumerik_opcua import OpcUaSecurity, open_sinumerik
    except ImportError as error:
        raise InputError(
            "machine_position: source sinumerik needs the asyncua package"
            " (pip install 'xmalign[opcua]')"
        ) from error
    security = OpcUaSecurity(
        policy=config.security_policy,
        mode=config.security_mode,
        certificate=config.certificate,
        private_key=config.private_key,
        server_certificate=config.server_certificate,
        identity=config.login,
        user=config.user,
        password=_password(config),
    )
    machine = open_sinumerik(
        config.endpoint,
        config.timeout_s or io_s,
        security,
        channel=config.channel,
        axis_indices=config.axes,
        length_unit=config.length_unit,
        settle_s=config.settle_s,
        standstill_tolerance_mm=config.standstill_mm,
        clock=clock,
        mode_group=config.mode_group,
    )
    closers.append(machine.close)
    return machine


def _password(config: SinumerikConfig) -> str | None:
    return secret_value(
        config.password, config.password_env, "machine_position.sinumerik.password_env"
    )


def secret_value(value: SecretStr | None, env: str | None, env_key: str) -> str | None:
    """A password given in the file (``value``) or in the environment variable ``env``
    (``env_key`` names that key in errors); None when neither is given."""
    if value is not None:
        return value.get_secret_value()
    if env is None:
        return None
    text = os.environ.get(env)
    if text is None:
        raise InputError(f"{env_key}: the environment variable {env} is not set")
    return text
