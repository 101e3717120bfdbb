"""Hardware side of dffd: VISCA serial driver, frame capture, USB discovery, simulated camera.

Nothing in this package imports :mod:`dffd`.
"""
