"""The service: the wiring that opens a board's devices and loads or builds its bundles, and the one frame
loop that does I/O (camera -> pipeline -> link, network, STATUS). The board config is :mod:`optitac_edge.config`."""
