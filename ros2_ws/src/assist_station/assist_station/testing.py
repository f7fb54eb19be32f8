"""Helpers for tests and benches that drive the station page in headless Chromium (Selenium)."""
from __future__ import annotations

import base64
import os
import shutil
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
