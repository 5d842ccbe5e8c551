"""A real headless Chromium for the console's browser tests (Debian's chromium, chromium-driver, python3-selenium).

``Browser(procs, folder)`` starts ``chromedriver`` on a free loopback port as a child of the test's
``ProcessGroup`` (its own session, stopped as a group and checked gone), and a Chromium through it with a fresh
``--user-data-dir`` under ``folder`` and the flags that keep it off the network (no background requests, no
component updates, no sync). ``quit()`` ends the browser and checks that no process mentioning its profile
folder is left. ``recorder()`` keeps a screenshot of each state a test names (``shot(name)``); ``save(folder)``
writes them all, plus the state at that moment, when the test failed.
"""

import json
import os

from selenium import webdriver

from .lifecycle import processes_mentioning
from .polling import wait_until
from .ports import free_port, port_accepts

CHROMIUM = "/usr/bin/chromium"
CHROMEDRIVER = "/usr/bin/chromedriver"
FLAGS = ["--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--disable-gpu",
         "--disable-background-networking", "--disable-component-update", "--disable-sync", "--no-first-run",
         "--disable-default-apps", "--disable-extensions", "--no-default-browser-check", "--lang=en-GB"]


class Browser:
    def __init__(self, procs, folder, width=1280, height=900):
        self.procs = procs
        self.folder = str(folder)
        self.profile = os.path.join(self.folder, "chromium-profile")
        os.makedirs(self.profile, exist_ok=True)
        port = free_port()
        self.driver_process = procs.start([CHROMEDRIVER, f"--port={port}", "--allowed-ips=127.0.0.1"],
                                          env={"PATH": "/usr/bin:/bin", "HOME": self.folder}, name="chromedriver")
        wait_until(lambda: port_accepts(port), timeout=20, message="chromedriver to listen")
        options = webdriver.ChromeOptions()
        options.binary_location = CHROMIUM
        for flag in FLAGS + [f"--user-data-dir={self.profile}", f"--window-size={width},{height}"]:
            options.add_argument(flag)
        options.set_capability("goog:loggingPrefs", {"browser": "ALL", "performance": "ALL"})
        self.driver = webdriver.Remote(command_executor=f"http://127.0.0.1:{port}", options=options)
        self.driver.set_page_load_timeout(60)
        self.driver.set_script_timeout(30)

    # -- what the page did ------------------------------------------------------------------------------
    def console_errors(self):
        """Entries of the browser's console at level SEVERE since the last call (JS errors, failed loads)."""
        return [e for e in self.driver.get_log("browser") if e.get("level") == "SEVERE"]

    def requested_urls(self):
        """Every URL the page asked for since the last call (Chromium's network log)."""
        urls = []
        for entry in self.driver.get_log("performance"):
            message = json.loads(entry["message"])["message"]
            if message.get("method") == "Network.requestWillBeSent":
                urls.append(message["params"]["request"]["url"])
        return urls

    def js(self, script, *args):
        return self.driver.execute_script(script, *args)

    # -- screenshots ------------------------------------------------------------------------------------
    def recorder(self):
        return Screenshots(self.driver)

    def quit(self):
        try:
            self.driver.quit()
        except Exception:  # chromedriver already gone: stopping its group below ends the browser too
            pass
        finally:
            self.procs.stop(self.driver_process)
            wait_until(lambda: not processes_mentioning(self.profile), timeout=15,
                       message=f"every Chromium process to be gone: {processes_mentioning(self.profile)}")


class Screenshots:
    """Screenshots of the states a test went through, in memory until ``save`` writes them."""

    def __init__(self, driver):
        self.driver = driver
        self.shots = []

    def __call__(self, name):
        self.shots.append((name, self.driver.get_screenshot_as_png()))

    def save(self, folder):
        os.makedirs(str(folder), exist_ok=True)
        try:
            self("at-failure")
        except Exception:  # the browser itself may be what failed
            pass
        for index, (name, png) in enumerate(self.shots):
            with open(os.path.join(str(folder), f"{index:02d}-{name}.png"), "wb") as f:
                f.write(png)
