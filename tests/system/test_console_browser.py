"""The console in a real headless Chromium against a real master and real robot agents on loopback (issue 11).

One master and one browser serve the whole module (both are slow to start); each test starts the robot agents it
needs on its own address and stops them. Every state a test looks at is screenshotted and the screenshots are
written to the test's folder when it fails. With ``RCMP_DOC_SCREENSHOTS=1`` the tests also refresh the
screenshots of docs/CONSOLE.md.
"""

import os
import subprocess
import urllib.parse

import pytest
from selenium.webdriver.common.by import By
from selenium.webdriver.common.keys import Keys
from selenium.webdriver.support.ui import Select

from demo.run_demo import SERVICE_LOGIC as DEMO_LOGIC, console_link
from tests.support.browser import Browser
from tests.support.lifecycle import Platform
from tests.support.paths import REPO
from tests.support.polling import wait_until
from tests.support.processes import ProcessGroup, ros_env

ROOT = REPO
DOC_SHOTS = os.environ.get("RCMP_DOC_SCREENSHOTS") == "1"


def module_procs(tmp_path_factory, name):
    return ProcessGroup(log_dir=str(tmp_path_factory.mktemp(name)))


@pytest.fixture(scope="module")
def platform(tmp_path_factory):
    plat = Platform(module_procs(tmp_path_factory, "platform-procs"), tmp_path_factory.mktemp("console-platform"))
    try:
        plat.master.start()
        yield plat
    finally:
        plat.stop_all_and_check_nothing_left()


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    procs = module_procs(tmp_path_factory, "browser-procs")
    try:
        chromium = Browser(procs, tmp_path_factory.mktemp("console-browser"))
        yield chromium
        chromium.quit()
    finally:
        procs.stop_all()


@pytest.fixture
def page(browser, platform, tmp_path, request):
    """The console, freshly loaded; screenshots of the states the test names, kept when it fails."""
    browser.driver.get("about:blank")
    browser.requested_urls(), browser.console_errors()   # only what the console does counts
    browser.driver.get(platform.master.base_url + "/console/")
    wait_until(lambda: browser.js("return document.body.dataset.seq && document.getElementById('live').textContent")
               == "live", timeout=15, message="the console to show the platform, live")
    shot = browser.recorder()
    yield shot
    report = getattr(request.node, "rep_call", None)
    if report is None or report.failed:
        shot.save(tmp_path / "screenshots")


def row_cells(browser, table, name):
    """The texts of the cells of row ``name`` of table ``table`` (None when there is no such row)."""
    return browser.js("""
        const row = document.querySelector(`#${arguments[0]} tr[data-name="${CSS.escape(arguments[1])}"]`);
        return row ? Array.from(row.cells, (c) => c.textContent) : null;""", table, name)


def stop_robot(platform, name):
    robot = platform.robots.pop(name)
    assert robot.stop() == 0


def test_the_page_loads_with_no_javascript_error_and_no_request_to_another_origin(browser, platform, page):
    origin = platform.master.base_url
    assert browser.js("return document.getElementById('live').textContent") == "live"
    assert "fiware_base" in browser.driver.find_element(By.ID, "logics").text
    errors = browser.console_errors()
    assert errors == []
    urls = browser.requested_urls()
    assert origin + "/console/" in urls and origin + "/console/console.js" in urls
    assert origin + "/console/api/events" in urls
    foreign = [u for u in urls if not (u.startswith(origin + "/") or u.startswith("data:"))]
    assert foreign == []
    page("overview")
    # a phone's width: nothing wider than the screen but the tables, which scroll in their own box
    browser.driver.set_window_size(390, 844)
    try:
        overflow = browser.js("return document.documentElement.scrollWidth - document.documentElement.clientWidth")
        page("phone")
        assert overflow <= 1
    finally:
        browser.driver.set_window_size(1280, 900)


def test_a_robot_started_after_the_page_loaded_appears_connected_then_paired(browser, platform, page):
    platform.provision_logic("console_talk", sn_list=[
        {"sn_package": "robotics_test", "sn_type": "talker.py", "sn_name": "body", "sn_params": "_topic:=chat",
         "sn_side": "R"}])
    platform.provision_robot("bot_live", "console_talk")
    wait_until(lambda: row_cells(browser, "robots", "bot_live"), timeout=5, message="the new robot's row")
    assert row_cells(browser, "robots", "bot_live")[2:4] == ["not connected", "not paired"]
    # every state the row shows from now on, and a marker that a reload would lose
    browser.js("""
        window.stillTheSamePage = true;
        window.seenStates = [];
        const record = () => {
          const row = document.querySelector('#robots tr[data-name="bot_live"]');
          const cells = row ? Array.from(row.cells, (c) => c.textContent).slice(2, 4).join(" / ") : "";
          if (window.seenStates[window.seenStates.length - 1] !== cells) window.seenStates.push(cells);
        };
        new MutationObserver(record).observe(document.querySelector('#robots tbody'),
                                             {childList: true, subtree: true, characterData: true});""")
    robot = platform.robot("bot_live", "127.0.0.2").start()
    try:
        wait_until(lambda: row_cells(browser, "robots", "bot_live")[3] == "paired", timeout=30,
                   message=f"the page to show bot_live paired (seen {browser.js('return window.seenStates')})")
        page("paired")
        seen = browser.js("return window.seenStates")
        assert "connected / not paired" in seen, seen
        assert seen.index("connected / not paired") < seen.index("connected / paired"), seen
        assert browser.js("return window.stillTheSamePage") is True
        assert row_cells(browser, "robots", "bot_live")[5] == "127.0.0.2"
    finally:
        stop_robot(platform, "bot_live")
    wait_until(lambda: row_cells(browser, "robots", "bot_live")[2] == "not connected", timeout=15,
               message="the page to show bot_live gone")
    assert robot.process.returncode == 0
    assert platform.remove_robot("bot_live")[0] == 200


def test_provisioning_through_the_forms_and_the_rdapi_sentence_for_an_invalid_name(browser, platform, page):
    driver = browser.driver
    # labels name the RDAPI fields
    labels = [label.text for label in driver.find_elements(By.CSS_SELECTOR, "#provision-robot label")]
    assert any("pi_name" in t for t in labels) and any("pi_service_logic" in t for t in labels)

    # a service logic with one node, typed and submitted from the keyboard
    driver.find_element(By.ID, "pl-slg_name").send_keys("form_logic")
    driver.find_element(By.ID, "add-node").send_keys(Keys.ENTER)
    fields = {"sn_name": "walker", "sn_package": "robotics_test", "sn_type": "talker.py", "sn_params": "_topic:=w"}
    for name, value in fields.items():
        field = driver.find_element(By.CSS_SELECTOR, f"#sn-rows input[name={name}]")
        label = driver.find_element(By.CSS_SELECTOR, f"label[for='{field.get_attribute('id')}']")
        assert name in label.text
        field.send_keys(value)
    Select(driver.find_element(By.CSS_SELECTOR, "#sn-rows select[name=sn_side]")).select_by_value("R")
    page("logic-form-filled")
    driver.find_element(By.ID, "pl-slg_name").send_keys(Keys.ENTER)
    wait_until(lambda: "provisioned" in driver.find_element(By.CSS_SELECTOR, "#provision-logic .form-ok").text,
               timeout=10, message="the logic form to say OK")
    status, answer = platform.master.get("/service_logic/read?slg_name=form_logic")
    assert status == 200 and answer["reason"]["sn_list"] == [dict(fields, sn_side="R")]
    wait_until(lambda: driver.find_elements(By.CSS_SELECTOR, '#logics [data-name="form_logic"]'), timeout=5,
               message="the new logic on the page")

    # a robot with it
    driver.find_element(By.ID, "pr-pi_name").send_keys("form_bot")
    driver.find_element(By.ID, "pr-pi_service_logic").send_keys("form_logic", Keys.ENTER)
    wait_until(lambda: row_cells(browser, "robots", "form_bot"), timeout=10, message="form_bot on the page")
    assert platform.state("form_bot") == (False, False)
    page("robot-provisioned")

    # an invalid name: the RDAPI's own sentence beside the form, nothing provisioned
    before = platform.instances()
    bad = {"pi_name": "bad name!", "pi_service_logic": "form_logic"}
    status, answer = platform.master.post("/platform_instance/provisioning", bad)
    assert status == 400
    driver.find_element(By.ID, "pr-pi_name").send_keys(bad["pi_name"])
    driver.find_element(By.ID, "pr-pi_service_logic").send_keys(bad["pi_service_logic"], Keys.ENTER)
    error = wait_until(lambda: driver.find_element(By.CSS_SELECTOR, "#provision-robot .form-error").text,
                       timeout=10, message="the form's error")
    page("invalid-name")
    assert error == answer["reason"]
    assert platform.instances() == before

    # removal through the form
    driver.find_element(By.ID, "rr-pi_name").send_keys("form_bot", Keys.ENTER)
    wait_until(lambda: row_cells(browser, "robots", "form_bot") is None, timeout=10, message="form_bot to go")
    assert "form_bot" not in platform.instances()
    driver.find_element(By.ID, "rl-slg_name").send_keys("form_logic", Keys.ENTER)
    wait_until(lambda: not driver.find_elements(By.CSS_SELECTOR, '#logics [data-name="form_logic"]'), timeout=10,
               message="form_logic to go")
    assert platform.master.get("/service_logic/read?slg_name=form_logic")[0] == 404


def item_cells(browser, name):
    return browser.js("""
        const row = document.querySelector(`#rv-items tr[data-item="${CSS.escape(arguments[0])}"]`);
        return row ? Array.from(row.cells, (c) => c.textContent) : null;""", name)


def test_an_item_that_fails_shows_its_error_and_its_log(browser, platform, page):
    platform.provision_logic("console_broken", sn_list=[
        {"sn_package": "robotics_test", "sn_type": "crasher.py", "sn_name": "crash", "sn_params": "",
         "sn_side": "S"},
        {"sn_package": "robotics_test", "sn_type": "crasher.py", "sn_name": "crash_r", "sn_params": "",
         "sn_side": "R"}])
    platform.provision_robot("bot_broken", "console_broken")
    browser.driver.get(platform.master.base_url + "/console/#/robot/bot_broken")
    platform.robot("bot_broken", "127.0.0.3").start()
    try:
        wait_until(lambda: (item_cells(browser, "crash") or [""] * 4)[3] == "failed", timeout=30,
                   message="the page to show the crashed item failed")
        page("item-failed")
        cells = item_cells(browser, "crash")
        assert cells[:3] == ["crash", "node", "master"]
        assert "imaginary_lidar" in cells[4]
        # the space's reason and the R item's state come in pushes of their own, maybe after the S item's
        wait_until(lambda: "crash" in browser.driver.find_element(By.ID, "rv-summary").text, timeout=10,
                   message="the summary to name the failed item")
        summary = browser.driver.find_element(By.ID, "rv-summary").text
        assert "not paired" in summary and "crash" in summary
        wait_until(lambda: (item_cells(browser, "crash_r") or [""] * 5)[2:4] == ["bot_broken", "failed"],
                   timeout=10, message="the page to show the robot-side item failed on bot_broken")

        def log_of(item):
            found = browser.driver.find_elements(By.CSS_SELECTOR, f'#rv-logs [data-item="{item}"] pre')
            return found[0].text if found else ""
        wait_until(lambda: "imaginary_lidar" in log_of("crash"), timeout=10, message="the S item's log tail")
        # the R item's log is on the robot: the master asks it (item_tails) while the page shows the robot
        wait_until(lambda: "imaginary_lidar" in log_of("crash_r"), timeout=10, message="the R item's log tail")
    finally:
        stop_robot(platform, "bot_broken")
    assert platform.remove_robot("bot_broken")[0] == 200


def plot_geometry(browser):
    """Where the plot sits in the window, its axes (the page keeps them on the canvas) and its backing store."""
    return browser.js("""
        const canvas = document.getElementById('topic-canvas');
        const box = canvas.getBoundingClientRect();
        return {top: box.top, bottom: box.bottom, left: box.left, right: box.right, innerHeight, innerWidth,
                scrolled: window.scrollY, ratio: window.devicePixelRatio, cssWidth: canvas.clientWidth,
                cssHeight: canvas.clientHeight, width: canvas.width, height: canvas.height,
                axes: JSON.parse(canvas.dataset.axes || 'null')};""")


def test_the_demos_robot_link_opens_on_its_pose_drawn_in_view_with_equal_scales(browser, platform, page):
    platform.provision_logic(DEMO_LOGIC["slg_name"], sn_list=DEMO_LOGIC["sn_list"], sl_list=DEMO_LOGIC["sl_list"])
    platform.provision_robot("demo_robot", DEMO_LOGIC["slg_name"])
    platform.robot("demo_robot", "127.0.0.4").start()
    browser.driver.set_window_size(1280, 1000)     # a laptop's screen: the plot must be in view as the page opens
    try:
        platform.wait_state("demo_robot", True, True)
        # the link ./run demo prints, as it prints it: the page opens on /pose with nothing chosen by hand
        link = console_link(platform.master.base_url, "demo_robot")
        assert link.endswith("/console/#/robot/demo_robot?topic=/pose")
        browser.driver.get(link)
        select = browser.driver.find_element(By.ID, "topic-select")
        canvas = browser.driver.find_element(By.ID, "topic-canvas")
        wait_until(lambda: int(canvas.get_attribute("data-samples") or 0) >= 5, timeout=30,
                   message="samples of /pose on the page, without choosing the topic")
        assert Select(select).first_selected_option.get_attribute("value") == "/pose"
        first = (canvas.get_attribute("data-last"), browser.js("return arguments[0].toDataURL()", canvas))
        wait_until(lambda: canvas.get_attribute("data-last") != first[0], timeout=10, message="the pose to change")
        wait_until(lambda: browser.js("return arguments[0].toDataURL()", canvas) != first[1], timeout=10,
                   message="the drawing to change")
        page("pose-trail")
        assert canvas.is_displayed()
        assert "geometry_msgs/Pose2D" in browser.driver.find_element(By.ID, "topic-status").text
        wait_until(lambda: "/pose (geometry_msgs/Pose2D)" in [o.text for o in Select(select).options], timeout=10,
                   message="the topic list to name /pose with its type")

        where = plot_geometry(browser)
        # in view as the page opened: not below the fold, not scrolled to
        assert where["scrolled"] == 0 and 0 <= where["top"] and where["bottom"] <= where["innerHeight"], where
        assert where["right"] <= where["innerWidth"], where
        # drawn at the size it is shown, so its labels are the size they are written in
        assert (where["width"], where["height"]) == (round(where["cssWidth"] * where["ratio"]),
                                                     round(where["cssHeight"] * where["ratio"])), where
        axes = where["axes"]
        assert axes["x"]["title"] == "x (m)" and axes["y"]["title"] == "y (m)"
        assert int(axes["font"].split("px")[0]) >= 13, axes["font"]
        assert len(axes["x"]["ticks"]) >= 2 and len(axes["y"]["ticks"]) >= 2, axes
        # one metre is as long across as up
        assert abs(axes["x"]["pxPerUnit"] - axes["y"]["pxPerUnit"]) <= 1e-6 * axes["x"]["pxPerUnit"], axes

        # choosing another topic puts it in the address, so that the link shows what the page shows
        Select(select).select_by_value("/cmd_vel")
        wait_until(lambda: browser.js("return location.hash") == "#/robot/demo_robot?topic=/cmd_vel", timeout=5,
                   message="the address to name /cmd_vel")
        wait_until(lambda: "geometry_msgs/Twist" in browser.driver.find_element(By.ID, "topic-status").text,
                   timeout=20, message="/cmd_vel shown")
        page("cmd-vel-text")
        if DOC_SHOTS:
            browser.driver.get(link)
            canvas = browser.driver.find_element(By.ID, "topic-canvas")
            wait_until(lambda: int(canvas.get_attribute("data-samples") or 0) >= 270, timeout=60,
                       message="a whole circle (25 s at 0.5 m/s on 2 m) for the documentation")
            browser.driver.save_screenshot(os.path.join(ROOT, "docs", "console-robot.png"))
            browser.driver.get(platform.master.base_url + "/console/")
            wait_until(lambda: row_cells(browser, "robots", "demo_robot"), timeout=10, message="the overview")
            browser.driver.save_screenshot(os.path.join(ROOT, "docs", "console-overview.png"))
        assert [e for e in browser.console_errors() if "Uncaught" in e.get("message", "")] == []
    finally:
        browser.driver.set_window_size(1280, 900)
        stop_robot(platform, "demo_robot")
    assert platform.remove_robot("demo_robot")[0] == 200


def stroke_box(browser):
    """The bounding box (device pixels) of what the plot drew in the trail's blue, and how many pixels that is."""
    return browser.js("""
        const canvas = document.getElementById('topic-canvas');
        const {width, height} = canvas;
        const data = canvas.getContext('2d').getImageData(0, 0, width, height).data;
        let x0 = width, x1 = -1, y0 = height, y1 = -1, count = 0;
        for (let y = 0; y < height; y++) for (let x = 0; x < width; x++) {
          const i = 4 * (y * width + x), r = data[i], g = data[i + 1], b = data[i + 2];
          if (b > 150 && r < 90 && g < 150 && b - r > 100) {     // the trail's #0a58ca, edges included
            count++; x0 = Math.min(x0, x); x1 = Math.max(x1, x); y0 = Math.min(y0, y); y1 = Math.max(y1, y);
          }
        }
        return {x0, x1, y0, y1, count, ratio: window.devicePixelRatio};""")


def test_a_robot_going_round_a_circle_is_drawn_as_a_circle(browser, platform, page):
    """The demo's brain on a small fast circle (0.75 m at 1.5 m/s: one turn in about 3 s); the drawn trail's box
    is as wide as it is high, and as wide as the circle at the plot's scale."""
    brain, body = dict(DEMO_LOGIC["sn_list"][1]), DEMO_LOGIC["sn_list"][0]
    brain["sn_params"] = "_speed:=1.5 _radius:=0.75"
    platform.provision_logic("console_circle", sn_list=[body, brain])
    platform.provision_robot("circler", "console_circle")
    platform.robot("circler", "127.0.0.6").start()
    try:
        platform.wait_state("circler", True, True)
        browser.driver.get(console_link(platform.master.base_url, "circler"))
        canvas = browser.driver.find_element(By.ID, "topic-canvas")
        wait_until(lambda: int(canvas.get_attribute("data-samples") or 0) >= 50, timeout=40,
                   message="more than one turn of /pose on the page")
        page("circle")
        box = stroke_box(browser)
        width, height = box["x1"] - box["x0"], box["y1"] - box["y0"]
        assert box["count"] > 100 and height > 50, box
        assert 0.93 <= width / height <= 1.07, box
        scale = plot_geometry(browser)["axes"]["x"]["pxPerUnit"] * box["ratio"]
        assert abs(width - 2 * 0.75 * scale) <= 0.15 * 2 * 0.75 * scale, (box, scale)
    finally:
        stop_robot(platform, "circler")
    assert platform.remove_robot("circler")[0] == 200


def test_a_topic_carrying_nan_is_drawn_without_it_and_says_so(browser, platform, page, procs):
    """A pose that is sometimes NaN: the stream is strict JSON (before, a bare NaN broke the page's JSON.parse and
    it reconnected into the same error for ever), the finite poses are drawn, the others counted."""
    platform.provision_robot("nan_robot", "empty")
    platform.robot("nan_robot", "127.0.0.7").start()
    try:
        platform.wait_state("nan_robot", True, True)
        env = ros_env(master_uri=platform.space("nan_robot")[1]["ros_master_uri"])
        env["ROS_IP"] = "127.0.0.1"
        for pose in ("{x: .nan, y: 1.0, theta: .inf}", "{x: 2.0, y: 1.0, theta: 0.5}", "{x: 3.0, y: 1.5, theta: 0}"):
            procs.start(["/usr/bin/rostopic", "pub", "-r", "4", "/pose", "geometry_msgs/Pose2D", pose], env=env,
                        name="pose-publisher")
        browser.driver.get(console_link(platform.master.base_url, "nan_robot"))
        canvas = browser.driver.find_element(By.ID, "topic-canvas")
        wait_until(lambda: int(canvas.get_attribute("data-samples") or 0) >= 8
                   and int(canvas.get_attribute("data-skipped") or 0) >= 1
                   and int(canvas.get_attribute("data-skipped")) < int(canvas.get_attribute("data-samples")),
                   timeout=40, message="finite and NaN poses on the page")
        page("nan-pose")
        assert canvas.is_displayed()
        assert "not drawn (NaN or Infinity)" in browser.driver.find_element(By.ID, "topic-status").text
        # the finite poses are drawn (at the page's next animation frame, after the samples are counted)
        wait_until(lambda: stroke_box(browser)["count"] > 0, timeout=20, message="the finite poses drawn")
        assert browser.js("return document.getElementById('live').textContent") == "live"
        assert [e for e in browser.console_errors() if "Uncaught" in e.get("message", "")] == []
    finally:
        stop_robot(platform, "nan_robot")
    assert platform.remove_robot("nan_robot")[0] == 200


def test_leaving_the_page_and_coming_back_many_times_keeps_it_live(browser, platform, page):
    """A browser opens at most six connections to one server and keeps the pages it left for its Back button: a
    page kept with its streams open would, after a few visits, leave no connection for the next page. Each round
    leaves the page (its streams must close), changes the platform meanwhile, comes back with Back (the kept page
    must open its streams again and show the change), then opens a new console page."""
    console = platform.master.base_url + "/console/"
    added = []
    browser.driver.set_page_load_timeout(15)    # a page waiting for a free connection never loads in time
    try:
        for visit in range(8):
            browser.js("window.keptPage = arguments[0]", visit)
            browser.driver.get("about:blank")
            name = f"away_{visit}"
            platform.provision_robot(name, "empty")
            added.append(name)
            browser.driver.back()
            wait_until(lambda: row_cells(browser, "robots", name), timeout=10,
                       message=f"visit {visit}: the page, shown again, to show what changed while it was away")
            assert browser.js("return window.keptPage") == visit     # the kept page, not a reload
            browser.driver.get(console + f"?visit={visit}")             # a new page; the previous one is kept
            wait_until(lambda: row_cells(browser, "robots", name), timeout=10,
                       message=f"visit {visit}: a new console page to be live")
        page("after-visits")
    finally:
        browser.driver.set_page_load_timeout(60)
        for name in added:
            platform.remove_robot(name)


def test_a_server_vm_that_joins_and_leaves_shows_live(browser, platform, page):
    wait_until(lambda: row_cells(browser, "servers", platform.master.keys.get("name") or "master")
               or browser.js("return document.querySelectorAll('#servers tbody tr').length") >= 1, timeout=10,
               message="the master in the servers' list")
    server = platform.robot("console_server", "127.0.0.5", role="server").start()
    try:
        wait_until(lambda: row_cells(browser, "servers", "console_server"), timeout=20,
                   message="the server VM on the page")
        page("server-joined")
        cells = row_cells(browser, "servers", "console_server")
        assert cells[1:3] == ["connected", "127.0.0.5"]
    finally:
        stop_robot(platform, "console_server")
    # a server that went stays listed, not connected, until it comes back (rcmp_ms.server_rows)
    wait_until(lambda: (row_cells(browser, "servers", "console_server") or ["", ""])[1] == "not connected",
               timeout=15, message="the page to show the server VM gone")
    assert server.process.returncode == 0


def rcmp_token(platform, *args):
    """The real ``rcmp_n token ...`` on the master's home."""
    done = subprocess.run(["/usr/bin/python3", "-m", "rcm_platform", "--home", platform.master.home, "token", *args],
                          capture_output=True, text=True, timeout=60, env=platform.master.env(), cwd=ROOT)
    assert done.returncode == 0, done.stderr
    return done.stdout.strip()


def test_with_tokens_in_force_the_console_asks_for_one_and_sends_it(browser, platform, page):
    """Last of the module: it closes the RDAPI with a token and opens it again by revoking it."""
    driver = browser.driver
    token = rcmp_token(platform, "add", "console_test", "--role", "admin")
    try:
        wait_until(lambda: platform.master.get("/platform_instance/read")[0] == 401, timeout=10,
                   message="the RDAPI to need the token")
        assert platform.master.get("/console/api/events")[0] == 401     # the console's API too
        assert platform.master.get("/console/console.js")[0] == 200     # its static files stay public
        driver.get(platform.master.base_url + "/console/")
        wait_until(lambda: driver.find_element(By.ID, "token-box").is_displayed(), timeout=10,
                   message="the console to ask for a token")
        page("token-asked")
        assert "Bearer" in driver.find_element(By.ID, "token-error").text      # the RDAPI's sentence
        assert "token" in driver.find_element(By.CSS_SELECTOR, "label[for=token-input]").text
        driver.find_element(By.ID, "token-input").send_keys(token, Keys.ENTER)
        wait_until(lambda: driver.find_element(By.ID, "live").text == "live", timeout=10,
                   message="the stream to open with the token")
        driver.find_element(By.ID, "pr-pi_name").send_keys("token_bot")
        driver.find_element(By.ID, "pr-pi_service_logic").send_keys("empty", Keys.ENTER)
        wait_until(lambda: row_cells(browser, "robots", "token_bot"), timeout=10, message="token_bot on the page")
        page("provisioned-with-token")
    finally:
        rcmp_token(platform, "revoke", "console_test")
        wait_until(lambda: platform.master.get("/platform_instance/read")[0] == 200, timeout=10,
                   message="the RDAPI to be open again")
    assert "token_bot" in platform.instances()
    assert platform.remove_robot("token_bot")[0] == 200
