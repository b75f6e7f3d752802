"""Bring-up tools for a sensor on the bench: guided orientation, rig-driven collection, the MCU monitor.

Above the service and the simulator (they use cameras, bundles and the
simulator's virtual rig), below the command line.
"""
