"""The README as a newcomer follows it: its commands in order, as written,
in an environment without anything this project put there (no
`CARGO_TARGET_DIR`, no `OFFWORLD_*` variable, nothing of
`~/.cache/offworld-*` on `PATH`), each checked against the output the
README documents next to it.

Every command of the blocks walked here must be known to this file: a line
added to one of them fails the test until its documented output is checked
(or it is named as not run, with the reason). Run by `.ci/test` on its own,
after the other suites: the demo reinstalls the wheel, and the processes
block serves on the README's own port, 7447.
"""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
README = (REPO / "README.md").read_text(encoding="utf-8")


def section(title: str) -> str:
    """The README's `## title` section."""
    start = README.index(f"\n## {title}\n")
    end = README.find("\n## ", start + 1)
    return README[start : end if end >= 0 else len(README)]


def code_blocks(text: str, language: str) -> list[str]:
    return re.findall(rf"```{language}\n(.*?)```", text, re.S)


def commands(block: str) -> list[str]:
    """The command lines of a shell block, without their comments."""
    lines = []
    for line in block.splitlines():
        command = re.split(r"\s+#", line, maxsplit=1)[0].strip()
        if command and not command.startswith("#"):
            lines.append(command)
    return lines


def newcomer_env() -> dict[str, str]:
    """This environment as a fresh machine's: what the machine image has
    (the Rust toolchain, python3, pip), nothing the project set up."""
    env = {
        k: v
        for k, v in os.environ.items()
        if not k.startswith(("OFFWORLD", "CARGO_TARGET_DIR", "ZENOHD_", "MACHETE_", "RUST_LOG"))
    }
    env["PATH"] = os.pathsep.join(p for p in env["PATH"].split(os.pathsep) if "/.cache/offworld" not in p)
    return env


def run(command: str, cwd: Path, timeout: float) -> str:
    """Runs one README line through bash, as a newcomer pastes it; fails
    with its output unless it exits 0. On a timeout its whole process group
    is killed (cargo, maturin, Python: nothing keeps running or holds
    cargo's lock)."""
    process = subprocess.Popen(
        ["bash", "-c", command],
        cwd=cwd,
        env=newcomer_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        stdout, stderr = process.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        try:
            os.killpg(process.pid, signal.SIGKILL)
        except ProcessLookupError:  # it ended just then
            pass
        stdout, stderr = process.communicate()
        raise AssertionError(f"`{command}` ran past {timeout} s:\n{stdout}\n{stderr}") from None
    assert process.returncode == 0, f"`{command}` exited {process.returncode}:\n{stdout}\n{stderr}"
    return stdout


def test_the_two_commands_are_the_demo_and_the_tests_and_the_demo_prints_what_it_says():
    block = code_blocks(section("The two commands"), "bash")[0]
    assert commands(block) == ["bash .ci/demo", "bash .ci/test"]
    # The second is what CI runs (and what runs this file).
    assert (REPO / ".ci/run").read_text().strip().endswith("exec bash .ci/test")
    documented = block[block.index("It ends with:") :]
    assert "first observation (240, 320, 1) uint8" in documented
    out = run("bash .ci/demo", REPO, timeout=3600)
    # It ends with these lines, in this order.
    ending = [
        r"OffWorldMonolithDiscreteSim-v0: first observation \(240, 320, 1\) uint8 after \d+ ms",
        *(
            rf"episode {i}: return -?\d+ in \d+ steps \((?:time limit|reached the monolith|left the arena)\)"
            for i in range(3)
        ),
        r"\d+ steps in [\d.]+ s \(\d+ steps/s\)",
    ]
    last = out.strip().splitlines()[-len(ending) :]
    assert len(last) == len(ending), out
    for line, pattern in zip(last, ending):
        assert re.fullmatch(pattern, line), f"{line!r} is not {pattern!r}:\n{out}"
    # On a machine without the full build the demo's package is the lean one
    # the README describes: no live monitor and no TLS/QUIC links (a request
    # for either says how to get it) and no `offworld`; where the full build
    # exists (CI, after `.ci/setup`), the demo installs the full package and
    # takes nothing away.
    assert (
        "lean wheel without the live monitor, the `offworld` command or TLS/QUIC links to a lab"
        in " ".join(README.split())
    )
    if not (REPO / "py_client/wheel-data/scripts/offworld").exists():
        try:
            refused = run(
                "python3 -c 'import gymnasium, offworld_gym, offworld_gym.errors as e\n"
                "try:\n gymnasium.make(\"OffWorldMonolithDiscreteSim-v0\", rerun=\"x.rrd\")\n"
                "except e.BadRequest as x:\n print(x)'",
                REPO,
                timeout=120,
            )
            assert "built without the live monitor" in refused and "bash .ci/setup" in refused, refused
            refused = run(
                "python3 -c 'import offworld_gym, offworld_gym.errors as e\n"
                "try:\n offworld_gym.whoami(connect=\"quic/127.0.0.1:7447\", token=\"t\")\n"
                "except e.BadRequest as x:\n print(x)'",
                REPO,
                timeout=120,
            )
            assert "no TLS, QUIC or Unix-socket links" in refused and "bash .ci/setup" in refused, refused
        finally:
            # The second command begins with the full set-up (`.ci/test`
            # runs `.ci/setup`): what the README's other blocks use.
            run("bash .ci/setup", REPO, timeout=3600)
    assert run("offworld --version", REPO, timeout=60).startswith("offworld ")


def test_the_python_quickstart_runs_as_written(tmp_path: Path):
    quickstart = code_blocks(section("Using it from Python"), "python")[0]
    assert "# obs: uint8 (240, 320, 1)" in quickstart, "the documented observation"
    check = "\nassert obs.dtype.name == 'uint8' and obs.shape == (240, 320, 1), (obs.dtype, obs.shape)\n"
    check += "print('quickstart ok', reward, terminated, truncated, sorted(info))\n"
    script = tmp_path / "quickstart.py"
    script.write_text(quickstart + check)
    out = run(f"python3 {script}", tmp_path, timeout=300)
    assert out.startswith("quickstart ok "), out
    assert "'is_success'" in out and "'step'" in out, out


class Serving:
    """The README's `serve` line as a background process, its log kept."""

    def __init__(self, command: str, cwd: Path):
        self.process = subprocess.Popen(
            ["bash", "-c", f"exec {command}"],
            cwd=cwd,
            env=newcomer_env(),
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        self.log: list[str] = []
        self.ready = threading.Event()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.process.stderr is not None
        for line in self.process.stderr:
            self.log.append(line)
            if "serving; Ctrl-C" in line:
                self.ready.set()

    def wait_ready(self, within: float) -> None:
        deadline = time.monotonic() + within
        while not self.ready.wait(0.2):
            assert self.process.poll() is None, "serve exited:\n" + "".join(self.log)
            assert time.monotonic() < deadline, "serve did not come up:\n" + "".join(self.log)

    def stop(self) -> None:
        self.process.terminate()
        try:
            self.process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()


def test_the_pieces_run_as_processes_as_written(tmp_path: Path):
    block = code_blocks(section("Running the pieces as processes"), "bash")[0]
    lines = commands(block)
    serve, twin, envs, add, experiments, leaderboard, render = lines
    assert serve == "offworld --db offworld.db serve --env sim/monolith-0=MonolithDiscrete --embedded-twins"
    # Not run: the alternative to --embedded-twins (the same env twice).
    assert twin.startswith("offworld twin --env sim/monolith-0")
    assert "listening on tcp/127.0.0.1:7447" in block
    with socket.socket() as probe:
        taken = probe.connect_ex(("127.0.0.1", 7447)) == 0
    assert not taken, "something already listens on 127.0.0.1:7447, the README's port: stop it and run again"
    server = Serving(serve, tmp_path)
    try:
        server.wait_ready(within=120)
        listed = run(envs, tmp_path, timeout=60)
        assert re.search(r"^sim/monolith-0\s+MonolithDiscrete\s+free\b", listed, re.M), listed
        assert "sim/monolith-0  MonolithDiscrete  free" in block, "the documented listing"
        token = run(add, tmp_path, timeout=60)
        assert re.fullmatch(r"[0-9a-f]{32}\n", token), token
        assert run(experiments, tmp_path, timeout=60) == "no experiments yet in offworld.db\n"
        assert "no experiments yet in offworld.db" in block
        board = run(leaderboard, tmp_path, timeout=60)
        assert board == "no test-mode experiments on sim/monolith-0 yet: its leaderboard is empty\n", board
    finally:
        server.stop()
    assert any("listen=[\"tcp/127.0.0.1:7447\"]" in line for line in server.log), "".join(server.log)
    # A developer's line: the example renders into out/ of the checkout
    # (with --exact, the exact renderer's pair too). What it made is
    # removed after; what was there before stays.
    assert "writes out/rgb.png and out/depth.png" in block
    out = REPO / "out"
    made = [out / n for n in ("rgb.png", "depth.png", "rgb_exact.png", "depth_exact.png")]
    existed = {path for path in [out, *made] if path.exists()}
    try:
        run(render, REPO, timeout=1800)
        for path in made:
            assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", path
    finally:
        for path in made:
            if path not in existed:
                path.unlink(missing_ok=True)
        if out not in existed and out.exists() and not any(out.iterdir()):
            out.rmdir()


def test_the_sim_farm_runs_as_written():
    """`## Beyond one machine`: the router, twins and gym server as
    processes, a trainer's listing through the router."""
    block = code_blocks(section("Beyond one machine"), "bash")[0]
    setup, farm = commands(block)
    assert setup == "source .ci/env"
    assert farm == "offworld farm --twins 4 -- offworld gym envs"
    # One shell, as pasted: the farm needs what `source` put on PATH.
    listed = run(f"{setup} && {farm}", REPO, timeout=300)
    for i in range(4):
        assert re.search(rf"^sim/farm-{i}\s+MonolithDiscrete\s+free\s+controller,sim_twin$", listed, re.M), listed
    assert len(listed.splitlines()) == 4, listed
    assert "sim/farm-0   MonolithDiscrete   free   controller,sim_twin" in block, "the documented listing"
