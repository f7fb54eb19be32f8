"""Helpers for tests and benches that drive the station page in headless Chromium (Selenium)."""
from __future__ import annotations

import base64
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

# Debian's chromium as root on a machine without network: no sandbox, no GPU, no background traffic
CHROMIUM_FLAGS = ('--headless=new', '--no-sandbox', '--disable-gpu', '--disable-dev-shm-usage', '--disable-quic',
                  '--no-first-run', '--disable-background-networking', '--disable-component-update',
                  '--disable-sync', '--window-size=1000,700')
MISSING_BROWSER = ('chromium/chromedriver missing: run `make browser` (or `make test`), which installs the '
                   'Debian packages chromium and chromium-driver')


def start_browser(user_dir: Path):
    """A Selenium WebDriver on Debian's chromium + chromedriver (never downloads a browser or driver)."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    chromium, driver = shutil.which('chromium'), shutil.which('chromedriver')
    if not chromium or not driver:
        raise FileNotFoundError(MISSING_BROWSER)
    os.environ['SE_OFFLINE'] = 'true'          # Selenium Manager must not go online
    opts = webdriver.ChromeOptions()
    opts.binary_location = chromium
    for flag in CHROMIUM_FLAGS + (f'--user-data-dir={user_dir}',):
        opts.add_argument(flag)
    return webdriver.Chrome(service=Service(driver), options=opts)


def page_stats(driver) -> dict:
    """The page's window.stationStats (fps, frames, role, pose, held keys, latencies, ...)."""
    return driver.execute_script('return window.stationStats')


def canvas_png(driver, element_id: str = 'view') -> bytes:
    """A canvas's own pixels (no HTML overlays) as PNG bytes."""
    url = driver.execute_script(f"return document.getElementById('{element_id}').toDataURL('image/png')")
    return base64.b64decode(url.split(',', 1)[1])


def png_to_rgb(png: bytes) -> np.ndarray:
    """PNG bytes -> RGB uint8 array (H, W, 3)."""
    import cv2
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    if img is None:
        raise ValueError('not a PNG image')
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


class Proc:
    """A console-script node of this virtualenv on ROS domain `domain_id`, its output in the file `log`."""

    def __init__(self, exe: str, args: list[str], domain_id: int, log: Path):
        self.log_path, self._f = log, open(log, 'w')
        env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id), PYTHONUNBUFFERED='1')
        self.proc = subprocess.Popen([str(Path(sys.executable).parent / exe), '--ros-args', *args], env=env,
                                     stdout=self._f, stderr=subprocess.STDOUT, start_new_session=True)

    def log(self) -> str:
        """Everything the process printed so far."""
        self._f.flush()
        return self.log_path.read_text(errors='replace')

    def stop(self) -> int:
        """SIGINT, then SIGKILL if it does not exit within 10 s; its exit code."""
        from assist_sim.testing import stop_process
        code = stop_process(self.proc, 10.0)
        self._f.close()
        return code


def wait_for(predicate: Callable[[], object], timeout: float, interval: float = 0.02) -> bool:
    """Poll `predicate` until it is true (True) or `timeout` seconds pass (its last value, as a bool)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(interval)
    return bool(predicate())
