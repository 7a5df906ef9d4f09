"""Type stubs of the native half of ``offworld_gym`` (``py_client/src``).
Users call the typed Python layer; these stubs keep it checkable."""

from typing import Any

from ._config import NativeOptions

import numpy as np

__version__: str

# Errors are raised as the classes of `offworld_gym.errors`; Ctrl-C during
# any call that waits raises KeyboardInterrupt.

def task_names() -> list[str]:
    """The tasks the controller serves (``env_controller/tasks.toml``)."""

class NativeEnvs:
    """N envs of one task, opened on a deployment (embedded or remote).

    Every waiting call raises ``KeyboardInterrupt`` on Ctrl-C and leaves the
    envs usable; reset before stepping again (``py_client/src/lib.rs``)."""

    def __init__(self, options: NativeOptions) -> None: ...
    @property
    def spec(self) -> dict[str, Any]: ...
    def experiment_episodes(
        self, index: int = 0, timeout_s: float = 5.0
    ) -> tuple[dict[str, Any], list[dict[str, Any]]]: ...
    def __len__(self) -> int: ...
    def reset(self, seeds: list[int | None]) -> tuple[np.ndarray, list[dict[str, Any]]]: ...
    def step_without_autoreset(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]: ...
    def step_with_autoreset(
        self, actions: list[Any]
    ) -> tuple[np.ndarray, list[tuple[float, bool, bool, dict[str, Any], bool]]]: ...
    def close(self) -> None: ...

def list_envs(connect: str | None = None, timeout_s: float = 2.0) -> list[dict[str, Any]]: ...
def book(
    env_id: str,
    start_unix_ms: int,
    end_unix_ms: int,
    token: str,
    connect: str | None = None,
    timeout_s: float = 5.0,
) -> list[dict[str, Any]]: ...
def bookings(
    env_id: str, from_unix_ms: int, connect: str | None = None, timeout_s: float = 5.0
) -> list[dict[str, Any]]: ...
def cancel_booking(
    env_id: str, booking_id: int, token: str, connect: str | None = None, timeout_s: float = 5.0
) -> list[dict[str, Any]]: ...
def whoami(env_id: str | None, token: str, connect: str | None = None, timeout_s: float = 5.0) -> dict[str, Any]: ...
def my_bookings(token: str, connect: str | None = None, timeout_s: float = 5.0) -> list[dict[str, Any]]: ...
def run_command_line(argv: list[str]) -> int: ...
def experiments(
    env_id: str, token: str, connect: str | None = None, timeout_s: float = 5.0
) -> list[dict[str, Any]]: ...
def experiment_episodes(
    env_id: str,
    experiment_id: int,
    token: str,
    connect: str | None = None,
    timeout_s: float = 5.0,
) -> tuple[dict[str, Any], list[dict[str, Any]]]: ...
def leaderboard(env_id: str, connect: str | None = None, timeout_s: float = 5.0) -> list[dict[str, Any]]: ...
