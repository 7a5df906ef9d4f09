"""The lab's web page in a real headless browser against a real deployment:
both sim envs shown free, a lease taken from Python shown within 1 s
without a reload, free again once closed; the env page; a 404 page;
signing in with an access token, booking a slot on a real env, seeing it
listed, and an overlapping slot refused with the controller's reason;
against the emulated enclosure, the operator console refused to a
researcher, and an operator's e-stop acknowledged by the robot agent,
shown on the availability page, and released with its confirmation.

`OFFWORLD_WEB_SCREENSHOT=docs/img/web-envs.png` also saves the
availability page, with one env leased, for the docs;
`OFFWORLD_WEB_CONSOLE_SCREENSHOT=docs/img/web-console.png` the console
with the enclosure's e-stop engaged; `OFFWORLD_WEB_ENV_SCREENSHOT=
docs/img/web-env.png` an env's page with its live view while it steps;
`OFFWORLD_WEB_EXPERIMENT_SCREENSHOT=docs/img/web-experiment.png` an
experiment's page with its learning curve."""

from __future__ import annotations

import os
import struct
import threading
import urllib.error
import urllib.request

import gymnasium
import offworld_gym  # noqa: F401  (registers the envs)
import pytest
from conftest import ENCLOSURE_ENV, ENVS, REAL_ENV

from playwright.sync_api import expect

# The requirement: a lease taken from Python is on the page within 1 s.
LEASE_VISIBLE_MS = 1000
# Everything else only has to happen, within a bound that fails a hung test.
EVENTUALLY_MS = 10_000


def row(page, env_id: str):
    return page.locator(f'tr[data-env="{env_id}"]')


def test_a_lease_taken_from_python_shows_within_a_second_without_reload(lab, browser, tmp_path):
    page = browser.new_page(viewport={"width": 1200, "height": 520})
    page.goto(lab.url)
    for env_id in ENVS:
        expect(row(page, env_id)).to_have_attribute("data-state", "free", timeout=EVENTUALLY_MS)
        expect(row(page, env_id).locator('[data-field="state"]')).to_have_text("free")
        expect(row(page, env_id).locator('[data-field="task"]')).to_have_text("MonolithDiscrete")
    expect(page.locator("#live")).to_have_attribute("data-state", "live", timeout=EVENTUALLY_MS)
    # A reload would lose this.
    page.evaluate("window.notReloaded = true")

    env = gymnasium.make("OffWorldMonolithDiscreteSim-v0", connect=lab.endpoint, env_id=ENVS[0], resolution=(32, 32))
    try:
        # `make` returns holding the lease: from here the page has 1 s.
        expect(row(page, ENVS[0])).to_have_attribute("data-state", "leased", timeout=LEASE_VISIBLE_MS)
        expect(row(page, ENVS[0]).locator('[data-field="state"]')).to_have_text("leased")
        expect(row(page, ENVS[0]).locator('[data-field="state-detail"]')).to_contain_text("until")
        expect(row(page, ENVS[1])).to_have_attribute("data-state", "free")
        assert page.evaluate("window.notReloaded") is True

        env.reset(seed=1)
        # The reset's accuracy comes with the next status.
        expect(row(page, ENVS[0]).locator('[data-field="last-reset"]')).to_contain_text("° off", timeout=EVENTUALLY_MS)
        screenshot = os.environ.get("OFFWORLD_WEB_SCREENSHOT") or str(tmp_path / "web-envs.png")
        page.screenshot(path=screenshot, full_page=True)
        with open(screenshot, "rb") as png:
            header = png.read(24)
        assert header[:8] == b"\x89PNG\r\n\x1a\n"
        width, _ = struct.unpack(">II", header[16:24])
        assert width == 1200
    finally:
        env.close()
    expect(row(page, ENVS[0])).to_have_attribute("data-state", "free", timeout=EVENTUALLY_MS)
    expect(row(page, ENVS[0]).locator('[data-field="state"]')).to_have_text("free")
    assert page.evaluate("window.notReloaded") is True
    page.close()


def test_the_env_page_shows_its_state_and_an_empty_leaderboard(lab, browser):
    page = browser.new_page()
    response = page.goto(f"{lab.url}/envs/{ENVS[1]}")
    assert response is not None and response.status == 200
    expect(page.locator("h1")).to_have_text(ENVS[1])
    expect(row(page, ENVS[1])).to_have_attribute("data-state", "free")
    expect(page.locator("p.empty")).to_have_text("No test-mode experiment has finished an episode on this env yet.")
    # Only this env's row, kept live.
    expect(page.locator("tr[data-env]")).to_have_count(1)
    expect(page.locator("#live")).to_have_attribute("data-state", "live", timeout=EVENTUALLY_MS)
    expect(page.locator("tr[data-env]")).to_have_count(1)
    page.close()


def test_the_live_view_shows_a_stepping_envs_camera_and_overhead(lab, browser, tmp_path):
    env = gymnasium.make("OffWorldMonolithDiscreteSim-v0", connect=lab.endpoint, env_id=ENVS[0], resolution=(32, 32))
    stop = threading.Event()

    def keep_stepping() -> None:
        env.reset(seed=3)
        for step in range(20_000):  # bounded; stopped long before
            if stop.is_set():
                return
            _, _, terminated, truncated, _ = env.step(step % 3)
            if terminated or truncated:
                env.reset()

    stepper = threading.Thread(target=keep_stepping)
    stepper.start()
    try:
        page = browser.new_page(viewport={"width": 1200, "height": 760})
        page.set_default_timeout(EVENTUALLY_MS)
        page.goto(f"{lab.url}/envs/{ENVS[0]}")
        expect(page.locator("#live-view")).to_have_text("Live view")
        # Functions, not expression strings: the page's CSP forbids eval.
        loaded = "(view) => document.querySelector(`img[data-thumbnail=${view}]`).naturalWidth > 0"
        for view in ("camera", "overhead"):
            # A decoded image (the alt text has no natural width).
            page.wait_for_function(loaded, arg=view, timeout=EVENTUALLY_MS)
        # The camera's frame (the twin's 320×240) at most 240 px wide.
        width = page.evaluate("() => document.querySelector('img[data-thumbnail=camera]').naturalWidth")
        assert width == 160, width
        # The script keeps them fresh: a new request every few seconds.
        first = page.evaluate("() => document.querySelector('img[data-thumbnail=camera]').src")
        page.wait_for_function(
            "(first) => document.querySelector('img[data-thumbnail=camera]').src !== first",
            arg=first,
            timeout=EVENTUALLY_MS,
        )
        page.wait_for_function(loaded, arg="camera", timeout=EVENTUALLY_MS)
        screenshot = os.environ.get("OFFWORLD_WEB_ENV_SCREENSHOT") or str(tmp_path / "web-env.png")
        page.screenshot(path=screenshot, full_page=True)
        page.close()
    finally:
        stop.set()
        stepper.join(timeout=30)
        env.close()


def test_a_users_experiment_shows_its_episodes_and_learning_curve(lab, browser):
    episodes = 6
    env = gymnasium.make(
        "OffWorldMonolithDiscreteSim-v0",
        connect=lab.endpoint,
        env_id=ENVS[1],
        resolution=(32, 32),
        token=lab.token,
        experiment_name="curve-demo",
    )
    try:
        for episode in range(episodes):
            env.reset(seed=episode + 1)
            for step in range(200):  # bounded: the env truncates first
                _, _, terminated, truncated, _ = env.step((episode + step) % 3)
                if terminated or truncated:
                    break
    finally:
        env.close()
    page = browser.new_page(viewport={"width": 1200, "height": 900})
    page.set_default_timeout(EVENTUALLY_MS)
    sign_in(page, lab.url, lab.token)
    page.goto(f"{lab.url}/envs/{ENVS[1]}/experiments")
    experiment = page.locator("tr[data-experiment]")
    expect(experiment).to_have_count(1)
    expect(experiment.locator('[data-field="episodes"]')).to_have_text(str(episodes))
    experiment.locator("a").click()
    expect(page.locator("h1")).to_have_text("curve-demo")
    expect(page.locator("tr[data-episode]")).to_have_count(episodes)
    # The curve: one point per episode, drawn on the server.
    expect(page.locator("svg.curve circle")).to_have_count(episodes)
    screenshot = os.environ.get("OFFWORLD_WEB_EXPERIMENT_SCREENSHOT")
    if screenshot:
        page.screenshot(path=screenshot, full_page=True)
    page.close()


@pytest.mark.parametrize(
    "path",
    ["/envs/sim/nowhere", "/envs/lab/web-a", "/envs/sim/%FF", "/envs/sim/web-a/extra", "/no/such/page"],
)
def test_unknown_and_malformed_paths_are_404_pages(lab, browser, path):
    page = browser.new_page()
    response = page.goto(f"{lab.url}{path}")
    assert response is not None and response.status == 404
    expect(page.locator("h1")).to_have_text("404 · Not Found")
    page.close()


def test_the_page_sets_a_strict_content_security_policy(lab):
    with urllib.request.urlopen(lab.url, timeout=5) as response:
        policy = response.headers["Content-Security-Policy"]
        assert "script-src 'self'" in policy and "frame-ancestors 'none'" in policy
        assert response.headers["X-Content-Type-Options"] == "nosniff"
    request = urllib.request.Request(f"{lab.url}/api/envs", method="POST")
    try:
        urllib.request.urlopen(request, timeout=5)
        raise AssertionError("POST was accepted")
    except urllib.error.HTTPError as e:
        assert e.code == 405
    # The service keeps answering after the refusal.
    with urllib.request.urlopen(f"{lab.url}/api/envs", timeout=5) as response:
        assert response.status == 200


def test_a_signed_in_user_books_a_slot_and_an_overlap_is_refused(booking_lab, browser):
    page = browser.new_page(viewport={"width": 1200, "height": 720})
    page.set_default_timeout(EVENTUALLY_MS)
    # A wrong token is refused, saying why.
    page.goto(f"{booking_lab.url}/account")
    page.fill("#token", "not-a-token-at-all")
    page.click("button[type=submit]")
    expect(page.locator("#notice")).to_contain_text("unknown access token")
    assert "not-a-token-at-all" not in page.content()
    # The right one signs in; the cookie holding the session is HttpOnly.
    page.fill("#token", booking_lab.token)
    page.click("button[type=submit]")
    expect(page.locator("#signed-in")).to_contain_text("You are signed in")
    assert booking_lab.token not in page.content()
    assert page.evaluate("document.cookie") == "", "no script can read the session cookie"

    page.goto(f"{booking_lab.url}/envs/{REAL_ENV}/bookings")
    expect(page.locator("#no-bookings")).to_have_text("Nothing is booked.")
    # The form's default start (the next full hour, in the browser's zone), 30 minutes.
    page.fill("#minutes", "30")
    page.click("form[data-slot-form] button[type=submit]")
    expect(page.locator("#notice")).to_contain_text("Booked: slot #")
    mine = page.locator('tr[data-booking][data-user="alice"]')
    expect(mine).to_have_count(1)
    expect(mine.locator(".badge.yours")).to_have_text("yours")

    # The same start again overlaps: refused with the controller's reason.
    page.fill("#minutes", "45")
    response_status = []
    page.on("response", lambda r: response_status.append(r.status) if r.request.method == "POST" else None)
    page.click("form[data-slot-form] button[type=submit]")
    notice = page.locator("#notice")
    expect(notice).to_have_attribute("role", "alert")
    expect(notice).to_contain_text(f"Not booked: {REAL_ENV} is booked by alice from")
    assert response_status == [409], response_status
    expect(page.locator("tr[data-booking]")).to_have_count(1)
    screenshot = os.environ.get("OFFWORLD_WEB_BOOKINGS_SCREENSHOT")
    if screenshot:
        page.screenshot(path=screenshot, full_page=True)
    page.close()


def sign_in(page, url: str, token: str) -> None:
    page.goto(f"{url}/account")
    page.fill("#token", token)
    page.click("button[type=submit]")
    expect(page.locator("#signed-in")).to_contain_text("You are signed in")


def test_an_operator_e_stops_the_emulated_robot_from_the_console(enclosure_lab, browser):
    # A researcher signed in: no console link, and the console refuses them.
    researcher = browser.new_page()
    researcher.set_default_timeout(EVENTUALLY_MS)
    sign_in(researcher, enclosure_lab.url, enclosure_lab.researcher_token)
    expect(researcher.locator("#signed-in")).to_contain_text("as researcher")
    expect(researcher.locator("#console-link")).to_have_count(0)
    response = researcher.goto(f"{enclosure_lab.url}/console")
    assert response is not None and response.status == 403
    expect(researcher.locator("#refused")).to_have_text(
        "The operator console is for operators: researcher is not one."
    )
    researcher.close()

    # Someone watching the availability page while the operator acts: the
    # enclosure and both sim envs of the deployment.
    watcher = browser.new_page()
    watcher.set_default_timeout(EVENTUALLY_MS)
    watcher.goto(enclosure_lab.url)
    for env_id in (ENCLOSURE_ENV, *ENVS):
        expect(row(watcher, env_id)).to_have_attribute("data-state", "free")
    expect(watcher.locator("#live")).to_have_attribute("data-state", "live")

    ops = browser.new_page(viewport={"width": 1200, "height": 800})
    ops.set_default_timeout(EVENTUALLY_MS)
    sign_in(ops, enclosure_lab.url, enclosure_lab.operator_token)
    ops.click("#console-link")
    expect(ops.locator("h1")).to_have_text("Operator console")
    expect(ops.locator("#operator")).to_have_text("operator")
    enclosure = ops.locator(f'tr[data-env="{ENCLOSURE_ENV}"]')
    engage = enclosure.locator('form[data-action="engage"]')
    engage.locator('input[name="reason"]').fill("person in the enclosure")
    engage.locator("button").click()
    # The robot agent stopped the base, latched, and said so.
    expect(ops.locator("#notice")).to_contain_text(
        f"E-stop engaged on {ENCLOSURE_ENV}: acknowledged by robot_agent of {ENCLOSURE_ENV}"
    )
    expect(ops.locator(f'#acks li[data-component="robot_agent"][data-env="{ENCLOSURE_ENV}"]')).to_contain_text(
        "e-stops now engaged there: env"
    )
    expect(enclosure).to_have_attribute("data-state", "estopped")
    expect(enclosure.locator('[data-field="estop"]')).to_contain_text(
        "person in the enclosure (operator via the web console)"
    )
    # The watcher's page shows it without a reload.
    expect(row(watcher, ENCLOSURE_ENV)).to_have_attribute("data-state", "estopped")
    expect(row(watcher, ENCLOSURE_ENV).locator('[data-field="state-detail"]')).to_contain_text(
        "person in the enclosure"
    )
    screenshot = os.environ.get("OFFWORLD_WEB_CONSOLE_SCREENSHOT")
    if screenshot:
        ops.screenshot(path=screenshot, full_page=True)

    # The release asks for its confirmation: the browser will not send the
    # form without the box ticked, and the server would refuse it.
    release = enclosure.locator('form[data-action="release"]')
    release.locator('input[name="reason"]').fill("checked: all clear")
    release.locator("button").click()
    expect(ops.locator("#notice")).to_contain_text(f"E-stop engaged on {ENCLOSURE_ENV}")
    release.locator('input[name="confirm"]').check()
    release.locator("button").click()
    expect(ops.locator("#notice")).to_contain_text(
        f"E-stop released on {ENCLOSURE_ENV}: acknowledged by robot_agent of {ENCLOSURE_ENV}"
    )
    expect(row(watcher, ENCLOSURE_ENV)).to_have_attribute("data-state", "free")

    # The site's e-stop reaches every robot and twin of the deployment.
    site = ops.locator("#site-estop")
    site.locator('input[name="reason"]').fill("fire alarm drill")
    site.locator("button").click()
    expect(ops.locator("#notice")).to_contain_text("E-stop engaged on the site: acknowledged by")
    for component, env_id in (("robot_agent", ENCLOSURE_ENV), ("sim_twin", ENVS[0]), ("sim_twin", ENVS[1])):
        expect(ops.locator(f'#acks li[data-component="{component}"][data-env="{env_id}"]')).to_contain_text(
            "e-stops now engaged there: site"
        )
    for env_id in (ENCLOSURE_ENV, *ENVS):
        expect(row(watcher, env_id)).to_have_attribute("data-state", "estopped")
    # A researcher's Python session on a sim env is refused motion.
    env = gymnasium.make(
        "OffWorldMonolithDiscreteSim-v0", connect=enclosure_lab.sim_endpoint, env_id=ENVS[0], resolution=(32, 32)
    )
    try:
        with pytest.raises(offworld_gym.errors.OffWorldGymError, match="e-stop engaged"):
            env.reset(seed=1)
    finally:
        env.close()
    release = ops.locator("#site-estop form[data-action=\"release\"]")
    release.locator('input[name="reason"]').fill("drill over")
    release.locator('input[name="confirm"]').check()
    release.locator("button").click()
    expect(ops.locator("#notice")).to_contain_text("E-stop released on the site")
    for env_id in (ENCLOSURE_ENV, *ENVS):
        expect(row(watcher, env_id)).to_have_attribute("data-state", "free")
    ops.close()
    watcher.close()

