"""Devices and wire formats: cameras, links to the MCU, indentation rigs, the LED driver, systemd, files.

Every device follows one pattern (python-can's): a small base class, backends
chosen by name and imported only when used, ``with`` and an idempotent
``close()``. Nothing here touches hardware at import.
"""
