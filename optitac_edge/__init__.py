"""optitac-edge: OptiTac optical-fiber tactile sensor processing for robot grippers.

Nothing in this package touches hardware at import time.
"""

__version__ = "0.1.0"
