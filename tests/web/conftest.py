"""Fixtures of the web page's end-to-end tests: a deployment with two sim
envs (`offworld serve --embedded-twins`) and `lab_web` in front of
it, each a separate process on free loopback ports; the emulated enclosure
(`offworld emulate-enclosure`: controller, robot agent, tracker agent and the
emulated hardware as processes) with `lab_web` in front of it; and a
headless Debian chromium driven by Playwright."""

from __future__ import annotations

import contextlib
import json
import os
import queue
import random
import shutil
import signal
import socket
import subprocess
import threading
import time
import urllib.error
import urllib.request
from dataclasses import dataclass
from pathlib import Path

import pytest

ENVS = ("sim/web-a", "sim/web-b")
# The bookable env of the booking test: a real env whose controller answers
# bookings without a robot.
REAL_ENV = "real/web-bench"
# The env the emulated enclosure serves.
ENCLOSURE_ENV = "real/monolith-0"


def free_port() -> int:
    """A free port below Linux's ephemeral range (32768-60999), so no
    connection's local port can take it before the server listens."""
    rng = random.SystemRandom()
    for _ in range(64):
        port = rng.randrange(20000, 32000)
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    raise RuntimeError("no free loopback port in 20000-32000")


def binary(name: str) -> Path:
    target = Path(os.environ.get("CARGO_TARGET_DIR", Path.home() / ".cache/offworld-target"))
    path = target / "release" / name
    if not path.exists():
        pytest.fail(f"{path} is missing: build it with `cargo build --release --bins` (bash .ci/test does)")
    return path


def wait_until(what: str, check, proc: subprocess.Popen, timeout_s: float = 30.0):
    """Polls `check` (bounded) until it returns a truthy value; fails naming
    `what`, with the process's log if it died."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            err = proc.stderr.read().decode() if proc.stderr else ""
            raise RuntimeError(f"{what}: the process exited ({proc.returncode}): {err}")
        value = check()
        if value:
            return value
        time.sleep(0.1)
    raise RuntimeError(f"{what}: not within {timeout_s} s")


def stop(proc: subprocess.Popen) -> None:
    proc.terminate()
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout=10)


def get_json(url: str):
    with urllib.request.urlopen(url, timeout=5) as response:
        return json.load(response)


@dataclass
class Lab:
    endpoint: str
    url: str
    # A registered user's access token (`env_controller users add alice`).
    token: str


@dataclass
class BookingLab:
    url: str
    token: str


@contextlib.contextmanager
def web_in_front_of(endpoints: list[str], ready: str, is_ready, owners: list[subprocess.Popen]):
    """Runs `lab_web` connected to `endpoints` (a Zenoh peer of all of them
    when there are several: no router joins them here); yields its URL once
    `is_ready(listing)` holds for its `/api/envs` (named `ready`)."""
    http_port = free_port()
    mode = ["--mode", "peer"] if len(endpoints) > 1 else []
    connect = [arg for endpoint in endpoints for arg in ("--connect", endpoint)]
    web = subprocess.Popen(
        [str(binary("lab_web")), *mode, *connect, "--http", f"127.0.0.1:{http_port}"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    try:
        url = f"http://127.0.0.1:{http_port}"

        def listed() -> bool:
            for owner in owners:
                if owner.poll() is not None:
                    raise RuntimeError(f"{ready}: the deployment exited ({owner.returncode})")
            try:
                return is_ready(get_json(f"{url}/api/envs")["envs"])
            except (urllib.error.URLError, ConnectionError):
                return False

        wait_until(ready, listed, web)
        yield url
    finally:
        stop(web)


@contextlib.contextmanager
def serving(db: Path, envs: list[str]):
    """Runs `offworld serve` on `db` with `envs` (serve arguments);
    yields (its Zenoh endpoint, the process) once it listens."""
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    controller = subprocess.Popen(
        [str(binary("offworld")), "--db", str(db), "serve", *envs, "--listen", endpoint],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    try:

        def listening() -> bool:
            with socket.socket() as s:
                return s.connect_ex(("127.0.0.1", port)) == 0

        wait_until("offworld serve listens", listening, controller)
        yield endpoint, controller
    finally:
        stop(controller)


@contextlib.contextmanager
def running_lab(db: Path, envs: list[str], ready: str, is_ready):
    """Runs `offworld serve` on `db` with `envs` (serve arguments) and
    `lab_web` in front of it; yields (Zenoh endpoint, page URL) once
    `is_ready(listing)` holds for the page's `/api/envs` (named `ready`)."""
    with serving(db, envs) as (endpoint, controller):
        with web_in_front_of([endpoint], ready, is_ready, [controller]) as url:
            yield endpoint, url


@pytest.fixture()
def lab(tmp_path: Path):
    """Yields the Zenoh endpoint of a two-env deployment, the URL of
    `lab_web` serving it, once the page lists both envs, and the token of
    its user alice."""
    db = tmp_path / "gym.db"
    token = add_user(db, "alice")
    envs = [arg for env in ENVS for arg in ("--env", f"{env}=MonolithDiscrete")] + ["--embedded-twins"]
    both = lambda listed: [e["id"] for e in listed if e["task"]] == list(ENVS)  # noqa: E731
    with running_lab(db, envs, "lab_web lists both envs", both) as (endpoint, url):
        yield Lab(endpoint=endpoint, url=url, token=token)


def add_user(db: Path, name: str) -> str:
    """Registers `name` with `env_controller users add`; returns the token."""
    return (
        subprocess.run(
            [str(binary("env_controller")), "--db", str(db), "users", "add", name],
            check=True,
            capture_output=True,
            timeout=30,
        )
        .stdout.decode()
        .strip()
        .splitlines()[-1]
    )


@pytest.fixture()
def booking_lab(tmp_path: Path):
    """Yields the URL of `lab_web` in front of a controller serving the real
    env `REAL_ENV` (no robot: bookings need none) and the access token of its
    user `alice`, registered with `env_controller users add`."""
    db = tmp_path / "gym.db"
    token = add_user(db, "alice")

    def controller_listed(listed) -> bool:
        return any(e["id"] == REAL_ENV and "controller" in e["components"] for e in listed)

    envs = ["--env", f"{REAL_ENV}=MonolithDiscrete"]
    with running_lab(db, envs, "lab_web lists the real env's controller", controller_listed) as (_, url):
        yield BookingLab(url=url, token=token)


@pytest.fixture()
def browser():
    """Headless Debian chromium (Playwright's own browser download is not
    reachable from these machines)."""
    sync_api = pytest.importorskip("playwright.sync_api")
    executable = shutil.which("chromium") or "/usr/bin/chromium"
    if not Path(executable).exists():
        pytest.fail("chromium is missing: bash .ci/setup installs Debian's chromium")
    with sync_api.sync_playwright() as playwright:
        # No sandbox: CI runs as root, where chromium refuses to start with one.
        browser = playwright.chromium.launch(executable_path=executable, args=["--no-sandbox"])
        try:
            yield browser
        finally:
            browser.close()


@dataclass
class EnclosureLab:
    url: str
    researcher_token: str
    operator_token: str
    # The sim envs' controller (a gym client connects here).
    sim_endpoint: str


@pytest.fixture()
def enclosure_lab(tmp_path: Path):
    """Yields `lab_web` in front of one deployment of the emulated enclosure
    (`ENCLOSURE_ENV`: the real stack's processes driving emulated hardware)
    and two sim envs (`ENVS`, another controller with embedded twins), with
    the tokens of the enclosure's researcher and operator, once the page
    lists all three envs and the enclosure's robot agent."""
    launcher = subprocess.Popen(
        [str(binary("offworld")), "emulate-enclosure", "--task", "MonolithDiscrete"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    lines: queue.Queue[str] = queue.Queue()
    # Drained all along: a full pipe would block the launcher's logging.
    threading.Thread(target=lambda: [lines.put(line) for line in launcher.stderr], daemon=True).start()
    said: dict[str, str] = {}
    try:
        deadline = time.monotonic() + 120
        wanted = ("OFFWORLD_GYM_CONNECT", "OFFWORLD_GYM_ACCESS_TOKEN", "OFFWORLD_OPERATOR_TOKEN")
        while not all(key in said for key in wanted):
            if launcher.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"offworld emulate-enclosure did not come up ({launcher.returncode}): {said}")
            try:
                line = lines.get(timeout=0.5).strip()
            except queue.Empty:
                continue
            key, _, value = line.partition("=")
            if key in wanted:
                said[key] = value

        def all_listed(listed) -> bool:
            robot = any(e["id"] == ENCLOSURE_ENV and "robot_agent" in e["components"] for e in listed)
            sims = all(any(e["id"] == env and e["task"] for e in listed) for env in ENVS)
            return robot and sims

        sims = [arg for env in ENVS for arg in ("--env", f"{env}=MonolithDiscrete")] + ["--embedded-twins"]
        with serving(tmp_path / "sims.db", sims) as (sim_endpoint, sim_controller):
            endpoints = [said["OFFWORLD_GYM_CONNECT"], sim_endpoint]
            with web_in_front_of(
                endpoints, "lab_web lists the enclosure and both sim envs", all_listed, [launcher, sim_controller]
            ) as url:
                yield EnclosureLab(
                    url=url,
                    researcher_token=said["OFFWORLD_GYM_ACCESS_TOKEN"],
                    operator_token=said["OFFWORLD_OPERATOR_TOKEN"],
                    sim_endpoint=sim_endpoint,
                )
    finally:
        # Ctrl-C: the launcher stops every process of the deployment.
        launcher.send_signal(signal.SIGINT)
        try:
            launcher.wait(timeout=30)
        except subprocess.TimeoutExpired:
            launcher.kill()
            launcher.wait(timeout=10)

