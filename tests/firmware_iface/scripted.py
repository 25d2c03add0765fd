"""Scripted-protocol doubles in the style of PyMeasure's ``expected_protocol``.

A script is the exact list of requests a driver must make, with the answers to
give (an exception as the answer is raised). Any other request fails at once;
steps left over when the ``with`` block ends fail too, so a test pins the whole
sequence of the REGISTERS contract.
"""

from __future__ import annotations

from collections.abc import Sequence
from types import TracebackType
from typing import Any


class _Script:
    def __init__(self, steps: Sequence[tuple[Any, ...]]) -> None:
        self.steps = list(steps)
        self.done = 0

    def next(self, request: tuple[Any, ...]) -> Any:
        assert self.steps, f"unexpected request {request} after the {self.done} scripted steps"
        step = self.steps.pop(0)
        expected, answer = step[:-1], step[-1]
        assert request == expected, f"step {self.done + 1}: expected {expected}, got {request}"
        self.done += 1
        if isinstance(answer, BaseException):
            raise answer  # the device or the bus fails this request
        return answer

    def __enter__(self) -> _Script:
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        if kind is None:
            assert not self.steps, f"{len(self.steps)} scripted steps left over: {self.steps}"


class ExpectedRegisters(_Script):
    """A ``RegisterTransport`` that plays ``("read", address, count, words)`` and
    ``("write", address, words, None)`` steps."""

    device_name = "scripted unit"

    def read_registers(self, address: int, count: int) -> list[int]:
        return list(self.next(("read", address, count)))

    def write_registers(self, address: int, values: Sequence[int]) -> None:
        self.next(("write", address, list(values)))


class _Entry:
    def __init__(self, script: ExpectedSdo, index: int, subindex: int = 0) -> None:
        self.script, self.index, self.subindex = script, index, subindex

    def __getitem__(self, subindex: int) -> _Entry:
        return _Entry(self.script, self.index, subindex)

    @property
    def raw(self) -> int:
        return int(self.script.next(("read", self.index, self.subindex)))

    @raw.setter
    def raw(self, value: int) -> None:
        self.script.next(("write", self.index, self.subindex, value))


class ExpectedSdo(_Script):
    """A canopen node whose SDOs play ``("read", index, sub, value)`` and
    ``("write", index, sub, value, None)`` steps."""

    def __init__(self, node_id: int, steps: Sequence[tuple[Any, ...]]) -> None:
        super().__init__(steps)
        self.id = node_id
        self.sdo = self

    def __getitem__(self, index: int) -> _Entry:
        return _Entry(self, index)


class ExpectedLines(_Script):
    """A serial ``LineConnection`` that plays ``(command, reply)`` steps (reply b"": silence)."""

    def __init__(self, steps: Sequence[tuple[Any, ...]]) -> None:
        super().__init__(steps)
        self._reply = b""

    def reset_input_buffer(self) -> None:
        self._reply = b""

    def write(self, data: bytes) -> int:
        self._reply = self.next((data,))
        return len(data)

    def readline(self) -> bytes:
        reply, self._reply = self._reply, b""
        return reply


class ExpectedRshLines(_Script):
    """A linuxcncrsh ``LineLink`` that plays ``(request_line, reply_line)`` steps."""

    name = "scripted LinuxCNC"

    def ask(self, line: str) -> str:
        return self.next((line,))

    def close(self) -> None:
        pass
