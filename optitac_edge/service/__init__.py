"""The service: the board config, the wiring that opens devices and loads or builds the bundle,
and the one frame loop that does I/O (camera -> pipeline -> link)."""
