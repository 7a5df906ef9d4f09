"""Ctrl-C during a blocking call: a real Python process gets SIGINT while
it waits on a deployment that does not answer (the controller process is
stopped with SIGSTOP), raises ``KeyboardInterrupt`` at once, and its env or
the package is usable afterwards (``NativeEnvs`` in ``py_client/src/lib.rs``
says why)."""

from __future__ import annotations

import os
import queue
import signal
import subprocess
import sys
import textwrap
import threading
import time
from contextlib import contextmanager
from pathlib import Path

import pytest
from conftest import start_controller, stop

#: From SIGINT to the child's report: a hang detector, not a speed target
#: (the measured latency is tens of ms).
INTERRUPT_BOUND_S = 5.0
#: Time for the child to be inside the native wait before SIGINT.
SETTLE_S = 0.5

PRELUDE = textwrap.dedent(
    """
    import signal, sys, time
    import gymnasium
    import offworld_gym
    endpoint, env_id = sys.argv[1], sys.argv[2]
    # Ctrl-C as at a terminal even when the tests run in a background job,
    # whose children inherit SIGINT ignored (Python then installs no handler).
    signal.signal(signal.SIGINT, signal.default_int_handler)

    def make():
        return gymnasium.make(
            "OffWorldMonolithDiscreteSim-v0", connect=endpoint, env_id=env_id, resolution=(24, 32)
        )

    def say(*words):
        print(*words, flush=True)

    def wait_for_go():
        sys.stdin.readline()

    def interrupted(call):
        started = time.monotonic()
        try:
            call()
        except KeyboardInterrupt:
            say("interrupted", f"{time.monotonic() - started:.3f}")
        else:
            say("not interrupted")
    """
)


class Child:
    """A Python process driven line by line, every read bounded."""

    def __init__(self, script: str, tmp_path: Path, endpoint: str, env_id: str) -> None:
        path = tmp_path / "child.py"
        path.write_text(PRELUDE + textwrap.dedent(script))
        self.proc = subprocess.Popen(
            [sys.executable, str(path), endpoint, env_id],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        self.lines: queue.Queue[str | None] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.put(line.strip())
        self.lines.put(None)

    def expect(self, word: str, within_s: float) -> list[str]:
        try:
            line = self.lines.get(timeout=within_s)
        except queue.Empty:
            pytest.fail(f"no {word!r} from the child within {within_s} s")
        if line is None or line.split()[0] != word:
            pytest.fail(f"expected {word!r}, got {line!r}; stderr: {self.stderr()}")
        return line.split()

    def go(self) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write("\n")
        self.proc.stdin.flush()

    def interrupt(self) -> None:
        """SIGINT once the child is inside the call it announced."""
        time.sleep(SETTLE_S)
        self.proc.send_signal(signal.SIGINT)

    def stderr(self) -> str:
        if self.proc.poll() is None:
            return "(running)"
        assert self.proc.stderr is not None
        return self.proc.stderr.read()

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


@contextmanager
def child(script: str, tmp_path: Path, deployment: tuple[str, str]):
    c = Child(script, tmp_path, *deployment)
    try:
        yield c
    finally:
        c.kill()


@contextmanager
def frozen(controller_pid: int):
    """The controller stopped: it answers nothing until resumed."""
    os.kill(controller_pid, signal.SIGSTOP)
    try:
        yield
    finally:
        os.kill(controller_pid, signal.SIGCONT)


@pytest.fixture()
def controller(tmp_path: Path):
    """(pid, (endpoint, env_id)) of a sim deployment in another process."""
    env_id = "sim/interrupt-0"
    proc, endpoint = start_controller(tmp_path, env_id)
    try:
        yield proc.pid, (endpoint, env_id)
    finally:
        os.kill(proc.pid, signal.SIGCONT)
        stop(proc)


CALLS = {
    # The call to interrupt, then what must work once the controller is back.
    "reset": ("env.reset(seed=2)", "env.reset(seed=3); env.step(0); env.close()"),
    "step": ("env.step(0)", "env.reset(seed=3); env.step(0); env.close()"),
    # The abandoned close released the lease: the same env opens again.
    "close": ("env.close()", "env.close(); again = make(); again.reset(); again.close()"),
}


@pytest.mark.parametrize("call", CALLS)
def test_ctrl_c_interrupts_a_blocked_env_call_and_the_env_stays_usable(controller, tmp_path, call):
    pid, deployment = controller
    blocked, after = CALLS[call]
    script = f"""
        env = make()
        env.reset(seed=1)
        say("opened")
        wait_for_go()
        say("blocking")
        interrupted(lambda: {blocked})
        wait_for_go()
        {after}
        say("usable")
    """
    with child(script, tmp_path, deployment) as c:
        c.expect("opened", within_s=60)
        with frozen(pid):
            c.go()
            c.expect("blocking", within_s=10)
            c.interrupt()
            c.expect("interrupted", within_s=INTERRUPT_BOUND_S)
        c.go()
        c.expect("usable", within_s=60)
        assert c.proc.wait(timeout=30) == 0, c.stderr()


def test_ctrl_c_interrupts_a_blocked_make_and_the_package_stays_usable(controller, tmp_path):
    pid, deployment = controller
    script = """
        say("blocking")
        interrupted(make)
        wait_for_go()
        env = make()
        env.reset(seed=1)
        env.close()
        say("usable")
    """
    with child(script, tmp_path, deployment) as c:
        with frozen(pid):
            c.expect("blocking", within_s=60)
            c.interrupt()
            c.expect("interrupted", within_s=INTERRUPT_BOUND_S)
        c.go()
        c.expect("usable", within_s=60)
        assert c.proc.wait(timeout=30) == 0, c.stderr()


def test_an_uncaught_ctrl_c_ends_the_program(controller, tmp_path):
    pid, deployment = controller
    script = """
        env = make()
        say("opened")
        wait_for_go()
        say("blocking")
        env.reset()
    """
    with child(script, tmp_path, deployment) as c:
        c.expect("opened", within_s=60)
        with frozen(pid):
            c.go()
            c.expect("blocking", within_s=10)
            c.interrupt()
            signalled = time.monotonic()
            try:
                code = c.proc.wait(timeout=INTERRUPT_BOUND_S)
            except subprocess.TimeoutExpired:
                pytest.fail(f"still running {INTERRUPT_BOUND_S} s after SIGINT")
        assert time.monotonic() - signalled < INTERRUPT_BOUND_S
        # Python ends an uncaught KeyboardInterrupt by dying of SIGINT.
        assert code == -signal.SIGINT
        assert "KeyboardInterrupt" in c.stderr()
